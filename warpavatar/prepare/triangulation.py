"""Confidence-weighted multi-view triangulation (direct linear transform) with lens distortion and outlier views.

For one point seen at undistorted normalized image coordinates (x_v, y_v) by cameras v with world-to-camera
matrices P_v = [R_v | t_v] (3x4), the homogeneous world point X solves the stacked equations

    w_v (x_v P_v[2] - P_v[0]) X = 0,    w_v (y_v P_v[2] - P_v[1]) X = 0,

in the least-squares sense (the right singular vector of the smallest singular value). Working in normalized
coordinates weighs every view by angle, not by its focal length in pixels; the weight w_v is the 2D detector's
confidence. Views whose reprojection error stays above a threshold are dropped one at a time (the worst first)
while at least two views remain, so a view that tracked someone else does not drag the point.
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np

from warpavatar.prepare.calibration import CameraCalibration

__all__ = ["TriangulationResult", "triangulate_points", "correct_label_swaps", "solve_translation"]


@dataclasses.dataclass(frozen=True)
class TriangulationResult:
    """Triangulated points.

    Attributes:
        points: world points [m], shape [..., 3] float64; NaN where fewer than two views were usable.
        confidence: per point in [0, 1], shape [...]: the second largest confidence among the inlier views
            (a point is as trustworthy as its second-best view), 0 where not triangulated.
        reprojection_error_px: per view and point, distance [px] between the reprojected point and the
            (undistorted) observation, shape [V, ...]; NaN where the view had no observation.
        inlier_views: shape [V, ...] bool, which views the final solve used.
    """

    points: np.ndarray
    confidence: np.ndarray
    reprojection_error_px: np.ndarray
    inlier_views: np.ndarray


def _solve_weighted_dlt(normalized: np.ndarray, weights: np.ndarray, projections: np.ndarray) -> np.ndarray:
    # normalized: [V, N, 2]; weights: [V, N]; projections: [V, 3, 4]. Returns homogeneous points [N, 4].
    rows_x = normalized[..., 0:1] * projections[:, None, 2, :] - projections[:, None, 0, :]
    rows_y = normalized[..., 1:2] * projections[:, None, 2, :] - projections[:, None, 1, :]
    # Unit rows before weighting, so a view's influence is its weight alone.
    rows = np.stack([rows_x, rows_y], axis=1)  # [V, 2, N, 4]
    rows = rows / np.maximum(np.linalg.norm(rows, axis=-1, keepdims=True), 1e-12)
    rows = rows * weights[:, None, :, None]
    design = np.transpose(rows, (2, 0, 1, 3)).reshape(normalized.shape[1], -1, 4)  # [N, 2V, 4]
    _, _, vh = np.linalg.svd(design)
    return vh[:, -1, :]


def triangulate_points(
    pixels: np.ndarray,
    confidence: np.ndarray,
    cameras: list[CameraCalibration],
    *,
    min_confidence: float = 0.1,
    outlier_threshold_px: float | None = 20.0,
    undistort: bool = True,
) -> TriangulationResult:
    """Triangulate points observed by several calibrated cameras.

    Args:
        pixels: observations [px], shape [V, ...] + [2] (V views; e.g. [V, T, 33, 2] for T frames of 33
            landmarks), raw image coordinates of each camera; NaN for unseen.
        confidence: detector confidence in [0, 1], shape [V, ...]; observations below ``min_confidence`` or with
            NaN pixels are ignored.
        cameras: the V cameras, same order; their image size must be the one ``pixels`` refer to.
        min_confidence: confidence below which an observation is not used.
        outlier_threshold_px: reprojection error [px] above which the worst view of a point is dropped and the
            point re-solved (while at least two views remain); None keeps every view.
        undistort: remove each camera's lens distortion from ``pixels`` first (set False when the
            observations were made on undistorted images).

    Returns:
        A :class:`TriangulationResult`.

    Raises:
        ValueError: shapes disagree, fewer than two cameras, or non-finite confidences.
    """
    pixels = np.asarray(pixels, dtype=np.float64)
    confidence = np.asarray(confidence, dtype=np.float64)
    view_count = len(cameras)
    if view_count < 2:
        raise ValueError(f"triangulation needs at least two cameras, got {view_count}")
    if pixels.ndim < 2 or pixels.shape[-1] != 2 or pixels.shape[0] != view_count:
        raise ValueError(f"pixels must have shape [V={view_count}, ..., 2], got {pixels.shape}")
    if confidence.shape != pixels.shape[:-1]:
        raise ValueError(f"confidence must have shape {pixels.shape[:-1]}, got {confidence.shape}")
    if not np.isfinite(confidence).all():
        raise ValueError("confidence must be finite")
    point_shape = pixels.shape[1:-1]
    flat_pixels = pixels.reshape(view_count, -1, 2)
    flat_confidence = confidence.reshape(view_count, -1)
    point_count = flat_pixels.shape[1]

    # Undistorted pixels (for errors) and normalized coordinates (for the solve).
    undistorted = np.stack([
        camera.undistort_pixels(view_pixels) if undistort else view_pixels
        for camera, view_pixels in zip(cameras, flat_pixels)
    ])
    normalized = np.empty_like(undistorted)
    for view, camera in enumerate(cameras):
        K_inverse = np.linalg.inv(camera.K)
        homogeneous = np.concatenate([undistorted[view], np.ones((point_count, 1))], axis=-1)
        normalized[view] = (homogeneous @ K_inverse.T)[:, :2]
    usable = np.isfinite(normalized).all(axis=-1) & (flat_confidence >= min_confidence)
    weights = np.where(usable, flat_confidence, 0.0)
    normalized = np.where(usable[..., None], normalized, 0.0)
    projections = np.stack([camera.world_to_camera[:3, :] for camera in cameras])

    def reprojection_errors(points: np.ndarray) -> np.ndarray:
        errors = np.full((view_count, point_count), np.nan)
        for view, camera in enumerate(cameras):
            projected = camera.project(points, distort=False)
            errors[view] = np.linalg.norm(projected - undistorted[view], axis=-1)
        return errors

    points = np.full((point_count, 3), np.nan)
    errors = np.full((view_count, point_count), np.nan)
    for _ in range(max(view_count - 1, 1)):
        solvable = (weights > 0).sum(axis=0) >= 2
        points[:] = np.nan
        if solvable.any():
            homogeneous = _solve_weighted_dlt(normalized[:, solvable], weights[:, solvable], projections)
            scale = homogeneous[:, 3:4]
            with np.errstate(divide="ignore", invalid="ignore"):
                solved = homogeneous[:, :3] / scale
            solved[np.abs(scale[:, 0]) < 1e-12] = np.nan
            points[solvable] = solved
        errors = reprojection_errors(points)
        if outlier_threshold_px is None:
            break
        # Drop the worst inlier view of every point whose worst inlier error is too large and that keeps 2 views.
        inlier_errors = np.where(weights > 0, np.nan_to_num(errors, nan=np.inf), -np.inf)
        worst_view = np.argmax(inlier_errors, axis=0)
        worst_error = inlier_errors[worst_view, np.arange(point_count)]
        drop = (worst_error > outlier_threshold_px) & ((weights > 0).sum(axis=0) >= 3)
        if not drop.any():
            break
        weights[worst_view[drop], np.nonzero(drop)[0]] = 0.0

    # A point behind any camera that uses it is not a valid solution.
    for view, camera in enumerate(cameras):
        depth = points @ camera.rotation[2] + camera.translation[2]
        points[(weights[view] > 0) & ~(depth > 0)] = np.nan
    valid = np.isfinite(points).all(axis=-1)
    sorted_weights = np.sort(weights, axis=0)
    point_confidence = np.where(valid, sorted_weights[-2], 0.0)
    errors = np.where(np.isfinite(undistorted).all(axis=-1), errors, np.nan)
    return TriangulationResult(
        points=points.reshape(point_shape + (3,)),
        confidence=point_confidence.reshape(point_shape),
        reprojection_error_px=errors.reshape((view_count,) + point_shape),
        inlier_views=(weights > 0).reshape((view_count,) + point_shape),
    )


def correct_label_swaps(
    pixels: np.ndarray,
    confidence: np.ndarray,
    cameras: list[CameraCalibration],
    permutations: list[np.ndarray],
    *,
    min_error_px: float = 10.0,
    improvement: float = 0.5,
    rounds: int = 2,
    **triangulation_options,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Undo label swaps (a detector calling the left knee the right one) in views that disagree with the others.

    The points are triangulated; then, for every view, frame and candidate permutation of the labels (e.g. the
    arms' left/right pairs, the legs'), the view's observations of the points the permutation moves are
    compared with the reprojected triangulation: if relabeled they fit at most ``improvement`` times as badly
    as before (median error over those points) and the original error is at least ``min_error_px``, the
    relabeling is applied. The permutations should move disjoint sets of points; each is decided on its own.
    This repeats ``rounds`` times (the triangulation improves once the swaps are undone). Needs three views or
    more: with two, neither view can be blamed.

    Args:
        pixels: observations [px], shape [V, T, P, 2] (raw image coordinates unless ``undistort=False`` is passed).
        confidence: shape [V, T, P].
        cameras: the V cameras.
        permutations: candidate relabelings, each an index array of shape [P] (``new[..., p] = old[..., perm[p]]``)
            that is its own inverse (a set of pair exchanges).
        min_error_px: views fitting better than this are left alone.
        improvement: required error ratio (relabeled / original).
        rounds: triangulate-and-relabel passes.
        **triangulation_options: passed to :func:`triangulate_points`.

    Returns:
        ``(pixels, confidence, relabeled)``: relabeled copies and, per view, frame and permutation, whether it
        was applied (an odd number of times), shape [V, T, len(permutations)] bool.
    """
    pixels = np.array(pixels, dtype=np.float64, copy=True)
    confidence = np.array(confidence, dtype=np.float64, copy=True)
    if pixels.ndim != 4 or pixels.shape[-1] != 2:
        raise ValueError(f"pixels must have shape [V, T, P, 2], got {pixels.shape}")
    if confidence.shape != pixels.shape[:-1]:
        raise ValueError(f"confidence must have shape {pixels.shape[:-1]}, got {confidence.shape}")
    view_count, frame_count, point_count = pixels.shape[:3]
    permutations = [np.asarray(permutation, dtype=np.int64) for permutation in permutations]
    for permutation in permutations:
        if permutation.shape != (point_count,) or not np.array_equal(permutation[permutation], np.arange(point_count)):
            raise ValueError(f"each permutation must be a self-inverse reordering of the {point_count} points")
    relabeled = np.zeros((view_count, frame_count, len(permutations)), dtype=bool)
    if view_count < 3 or frame_count == 0:
        return pixels, confidence, relabeled
    undistort = triangulation_options.get("undistort", True)
    for _ in range(rounds):
        points = triangulate_points(pixels, confidence, cameras, **triangulation_options).points
        changed = False
        for view, camera in enumerate(cameras):
            observed = camera.undistort_pixels(pixels[view]) if undistort else pixels[view].copy()
            projected = camera.project(points, distort=False)  # [T, P, 2]
            for index, permutation in enumerate(permutations):
                moved = np.nonzero(permutation != np.arange(point_count))[0]
                if moved.size == 0:
                    continue
                original = np.linalg.norm(observed[:, moved] - projected[:, moved], axis=-1)
                swapped = np.linalg.norm(observed[:, permutation[moved]] - projected[:, moved], axis=-1)
                with np.errstate(all="ignore"), warnings.catch_warnings():
                    warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN frames
                    original_error = np.nanmedian(original, axis=-1)
                    swapped_error = np.nanmedian(swapped, axis=-1)
                apply = (original_error >= min_error_px) & (swapped_error < improvement * original_error)
                for frame in np.nonzero(apply)[0]:
                    pixels[view, frame] = pixels[view, frame, permutation]
                    confidence[view, frame] = confidence[view, frame, permutation]
                    observed[frame] = observed[frame, permutation]
                relabeled[view, apply, index] ^= True
                changed |= bool(apply.any())
        if not changed:
            break
    return pixels, confidence, relabeled


def solve_translation(
    relative_points: np.ndarray,
    pixels: np.ndarray,
    confidence: np.ndarray,
    K: np.ndarray,
    *,
    min_confidence: float = 0.3,
    iterations: int = 5,
) -> np.ndarray:
    """Place root-relative metric points in front of a camera: the translation t that best reprojects them.

    Solves, per frame, ``min_t sum_i w_i |project(K, X_i + t) - u_i|^2`` for points ``X_i`` already in the
    camera's orientation (MediaPipe's world landmarks are), a perspective-n-point problem with the rotation
    fixed. A weighted linear solve of ``x_i (Z_i + t_z) = X_i + t_x`` (and likewise y) starts Gauss-Newton
    iterations on the pixel error.

    Args:
        relative_points: points [m] in camera-aligned axes relative to the root, shape [T, P, 3]; NaN if missing.
        pixels: their observed image positions [px], shape [T, P, 2] (undistorted); NaN if missing.
        confidence: weights in [0, 1], shape [T, P]; points under ``min_confidence`` are not used.
        K: camera intrinsics, shape [3, 3].
        min_confidence: smallest confidence a point needs.
        iterations: Gauss-Newton steps after the linear solve.

    Returns:
        Translations [m], shape [T, 3] float64: camera-frame point = relative point + t. NaN for frames with
        fewer than 3 usable points.
    """
    relative_points = np.asarray(relative_points, dtype=np.float64)
    pixels = np.asarray(pixels, dtype=np.float64)
    confidence = np.asarray(confidence, dtype=np.float64)
    K = np.asarray(K, dtype=np.float64)
    if relative_points.ndim != 3 or relative_points.shape[-1] != 3:
        raise ValueError(f"relative_points must have shape [T, P, 3], got {relative_points.shape}")
    if pixels.shape != relative_points.shape[:-1] + (2,):
        raise ValueError(f"pixels must have shape {relative_points.shape[:-1] + (2,)}, got {pixels.shape}")
    if confidence.shape != relative_points.shape[:-1]:
        raise ValueError(f"confidence must have shape {relative_points.shape[:-1]}, got {confidence.shape}")
    if K.shape != (3, 3):
        raise ValueError(f"K must have shape [3, 3], got {K.shape}")
    usable = (
        np.isfinite(relative_points).all(axis=-1) & np.isfinite(pixels).all(axis=-1)
        & np.isfinite(confidence) & (confidence >= min_confidence)
    )
    weights = np.where(usable, confidence, 0.0)
    points = np.where(usable[..., None], relative_points, 0.0)
    homogeneous = np.concatenate([np.where(usable[..., None], pixels, 0.0), np.ones(pixels.shape[:-1] + (1,))], -1)
    normalized = (homogeneous @ np.linalg.inv(K).T)[..., :2]
    frame_count = points.shape[0]
    # Linear solve: rows [1, 0, -x] t = x Z - X and [0, 1, -y] t = y Z - Y.
    ones = np.ones_like(normalized[..., 0])
    zeros = np.zeros_like(ones)
    rows = np.concatenate([
        np.stack([ones, zeros, -normalized[..., 0]], axis=-1),
        np.stack([zeros, ones, -normalized[..., 1]], axis=-1),
    ], axis=1)  # [T, 2P, 3]
    rhs = np.concatenate([
        normalized[..., 0] * points[..., 2] - points[..., 0],
        normalized[..., 1] * points[..., 2] - points[..., 1],
    ], axis=1)
    row_weights = np.concatenate([weights, weights], axis=1)
    normal_matrix = np.einsum("tn,tna,tnb->tab", row_weights, rows, rows)
    normal_rhs = np.einsum("tn,tna,tn->ta", row_weights, rows, rhs)
    solvable = usable.sum(axis=1) >= 3
    translation = np.full((frame_count, 3), np.nan)
    if not solvable.any():
        return translation
    normal_matrix[~solvable] = np.eye(3)
    normal_rhs[~solvable] = 0.0
    estimate = np.linalg.solve(normal_matrix, normal_rhs[..., None])[..., 0]
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    observed = homogeneous[..., :2]
    for _ in range(iterations):
        camera = points + estimate[:, None, :]
        depth = np.maximum(camera[..., 2], 1e-6)
        u = fx * camera[..., 0] / depth + cx
        v = fy * camera[..., 1] / depth + cy
        residual = np.stack([u - observed[..., 0], v - observed[..., 1]], axis=-1)  # [T, P, 2]
        jacobian = np.zeros(points.shape[:2] + (2, 3))
        jacobian[..., 0, 0] = fx / depth
        jacobian[..., 0, 2] = -fx * camera[..., 0] / depth**2
        jacobian[..., 1, 1] = fy / depth
        jacobian[..., 1, 2] = -fy * camera[..., 1] / depth**2
        hessian = np.einsum("tp,tpka,tpkb->tab", weights, jacobian, jacobian) + 1e-9 * np.eye(3)
        gradient = np.einsum("tp,tpka,tpk->ta", weights, jacobian, residual)
        step = np.linalg.solve(hessian, gradient[..., None])[..., 0]
        estimate = estimate - np.where(solvable[:, None], step, 0.0)
    translation[solvable] = estimate[solvable]
    return translation
