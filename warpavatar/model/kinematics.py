"""Skeleton kinematics: rotations from and to axis-angle vectors, ancestor tables, a pose corrected
joint by joint in torch, any dtype (the pose-noise tool's float64 noise; pose refinement and test-time refinement
use the float32 kernels of :func:`warpavatar.ops.corrected_poses`, the same maths), and the corrections that smooth
a motion in time (the target pose refinement's prior pulls towards)."""

from __future__ import annotations

import torch

from warpavatar.geometry import quat_from_matrix, skeleton_levels

__all__ = ["axis_angle_to_matrix", "axis_angle_from_matrix", "ancestor_jumps", "posed_pivots",
           "rigid_poses", "corrected_transforms", "local_rotations", "smoothing_corrections"]


def axis_angle_to_matrix(vectors: torch.Tensor) -> torch.Tensor:
    """Rotation matrices [...,3,3] of axis-angle vectors [...,3] (angle = norm [rad]); smooth, with finite
    gradients, at zero."""
    angle_sq = (vectors * vectors).sum(-1, keepdim=True)[..., None]  # [...,1,1]
    small = angle_sq < 1e-8
    angle = torch.sqrt(torch.where(small, torch.ones_like(angle_sq), angle_sq))
    # sin(a)/a and (1 - cos(a))/a^2, by their Taylor series near zero
    first = torch.where(small, 1.0 - angle_sq / 6.0, torch.sin(angle) / angle)
    second = torch.where(small, 0.5 - angle_sq / 24.0, (1.0 - torch.cos(angle)) / torch.where(small, 1.0, angle_sq))
    x, y, z = vectors.unbind(-1)
    zero = torch.zeros_like(x)
    cross = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], dim=-1).reshape(*vectors.shape[:-1], 3, 3)
    identity = torch.eye(3, dtype=vectors.dtype, device=vectors.device).expand_as(cross)
    return identity + first * cross + second * (cross @ cross)


def axis_angle_from_matrix(rotations: torch.Tensor) -> torch.Tensor:
    """Axis-angle vectors [...,3] (angle in [0, pi] [rad]) of rotation matrices [...,3,3]: the inverse of
    :func:`axis_angle_to_matrix`, through the unit quaternion with w >= 0."""
    quats = quat_from_matrix(rotations)
    w, vector = quats[..., :1], quats[..., 1:]
    sine = vector.norm(dim=-1, keepdim=True)  # sin(angle / 2)
    small = sine < 1e-7
    # angle / sin(angle / 2), with its limit 2 / cos(angle / 2) for small angles
    factor = torch.where(small, 2.0 / w, 2.0 * torch.atan2(sine, w) / torch.where(small, 1.0, sine))
    return vector * factor


def ancestor_jumps(parents, *, device=None) -> list[torch.Tensor]:
    """Ancestor tables for composing transforms down the skeleton in ``ceil(log2(depth))`` batched steps.

    Entry ``r`` [J] holds each joint's ``2**r``-th ancestor, or ``J`` (one past the last joint) where there is
    none; entry 0 is the parent. There is at least one entry.

    Raises:
        ValueError: parents that do not form a forest.
    """
    parents = [int(p) for p in parents]
    count = len(parents)
    depth = len(skeleton_levels(parents))  # also rejects cycles
    jumps = [[count if p < 0 else p for p in parents]]
    while 2 ** len(jumps) < depth:
        last = jumps[-1]
        jumps.append([count if last[j] == count else last[last[j]] for j in range(count)])
    return [torch.as_tensor(jump, dtype=torch.long, device=device) for jump in jumps]


def posed_pivots(bone_transforms: torch.Tensor, heads: torch.Tensor) -> torch.Tensor:
    """The joints' pivots [...,J,3] in a pose: the rest pivots ``heads`` [J,3] moved by ``bone_transforms``
    [...,J,4,4] (the ``joint_positions`` of a poses.npz)."""
    return (bone_transforms[..., :3, :3] @ heads[:, :, None])[..., 0] + bone_transforms[..., :3, 3]


def rigid_poses(bone_transforms: torch.Tensor, heads: torch.Tensor) -> torch.Tensor:
    """Poses [...,J,4,4] made exactly rigid: each rotation part replaced by its nearest rotation (the orthogonal
    factor of its polar decomposition, in float64), each translation chosen so that the joint's pivot stays where
    it was. Products of float32 transforms down a skeleton drift from rigid (about 1e-3 in ``|R^T R - I|`` after
    a refined pose is refined again), which poses.npz readers refuse; not differentiable, for exports."""
    matrices = bone_transforms.detach().double()
    left, _, right = torch.linalg.svd(matrices[..., :3, :3])
    sign = torch.sign(torch.linalg.det(left @ right))
    left = torch.cat([left[..., :2], left[..., 2:] * sign[..., None, None]], dim=-1)  # a rotation, no reflection
    rotations = left @ right
    pivots = posed_pivots(matrices, heads.double())
    out = matrices.clone()
    out[..., :3, :3] = rotations
    out[..., :3, 3] = pivots - (rotations @ heads.double()[:, :, None])[..., 0]
    return out.to(bone_transforms.dtype)


def corrected_transforms(bone_transforms: torch.Tensor, heads: torch.Tensor, jumps: list[torch.Tensor],
                         rotation: torch.Tensor, translation: torch.Tensor) -> torch.Tensor:
    """Poses [...,J,4,4] (rest-to-posed transforms) with every joint turned by ``exp(rotation[..., j])`` in its own
    posed frame after its given rotation relative to its parent, and the roots moved by ``translation``; each
    child keeps its pivot's offset from its parent's pivot, in the parent's frame.

    Each joint's correction is a rigid motion of the world, a turn ``R_j exp(d_j) R_j^T`` about its given pivot;
    a joint moves by the composition of its ancestors' and its own, from the root down (then the root's shift),
    composed for all joints at once by pointer jumping over ``jumps`` (a few batched products, not one per level).

    Args:
        bone_transforms: [...,J,4,4] the given poses (any leading dimensions: several frames at once).
        heads: [J,3] rest-pose pivots [world units].
        jumps: :func:`ancestor_jumps` of the skeleton, on the device.
        rotation: [...,J,3] axis-angle corrections [rad].
        translation: [...,3] root offsets [world units].

    Returns:
        [...,J,4,4] the corrected poses (equal to the given ones where both corrections are zero).
    """
    count = bone_transforms.shape[-3]
    given_rotation = bone_transforms[..., :3, :3]
    pivots = posed_pivots(bone_transforms, heads)
    turn = given_rotation @ axis_angle_to_matrix(rotation) @ given_rotation.transpose(-1, -2)  # about the pivot
    is_root = (jumps[0] == count).to(bone_transforms.dtype)[:, None]
    shift = pivots - (turn @ pivots[..., None])[..., 0] + is_root * translation[..., None, :]
    eye = torch.eye(4, dtype=bone_transforms.dtype, device=bone_transforms.device)
    bottom = eye[3:4].expand(*shift.shape[:-1], 1, 4)
    motion = torch.cat([torch.cat([turn, shift[..., None]], dim=-1), bottom], dim=-2)  # [...,J,4,4] of the world
    identity = eye.expand(*motion.shape[:-3], 1, 4, 4)
    for jump in jumps:  # each joint's motion composed after its ancestors' (2**r more of them each round)
        motion = torch.cat([motion, identity], dim=-3)[..., jump, :, :] @ motion
    return motion @ bone_transforms



def local_rotations(bone_transforms: torch.Tensor, parents) -> torch.Tensor:
    """Each joint's rotation [...,J,3,3] relative to its parent's, ``R_parent^T R_j`` (a root's: its own), of poses
    [...,J,4,4]: what :func:`corrected_transforms` turns by ``exp(d_j)`` on the right."""
    rotations = bone_transforms[..., :3, :3]
    parents = torch.as_tensor([int(p) for p in parents], dtype=torch.long, device=rotations.device)
    parent_rotations = rotations[..., parents.clamp(min=0), :, :]
    local = parent_rotations.transpose(-1, -2) @ rotations
    return torch.where((parents < 0)[:, None, None], rotations, local)


_ROBUST_SCALE = 6.0
"""Residuals beyond this many times the median residual of a joint get no weight in the robust passes."""

_WINDOW_FRACTIONS = (1.0 / 6.0, 0.25, 1.0 / 3.0, 0.5, 2.0 / 3.0, 1.0)
"""The windows :func:`smoothing_corrections` chooses from, as fractions of the widest (a ladder of ratio 1.33-1.5:
the choice rounds a motion's fast part off by little, and averages a slow one's noise over up to six times the
narrowest window)."""

_CONFIDENCE = 2.5
"""Half-width of the confidence intervals of the window choice, in standard deviations of each estimate."""

_CHI2_3_MEDIAN = 2.366
"""Median of the chi-squared distribution with 3 degrees of freedom (a 3-vector of unit Gaussian noise, squared)."""


def _local_quadratic_fits(values: torch.Tensor, offsets: torch.Tensor, valid: torch.Tensor, *,
                          robust_passes: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Values at offset 0 of weighted quadratic fits in time, one per frame and channel, and their variance.

    Args:
        values: [T,K,C,3] the K neighbours' values of each frame's C channels (vectors).
        offsets: [T,K] the neighbours' times relative to the frame, scaled to [-1, 1].
        valid: [T,K] which neighbours exist.
        robust_passes: refits with bisquare weights of the previous fit's residual (Tukey's biweight, the
            residual scale taken per channel over all frames), so that a frame the estimator got badly wrong
            does not drag its neighbours' targets.

    Returns:
        ``(value [T,C,3], variance [T,C])``: the fitted values at offset 0 and their variance per component for
        values of unit variance, independent from frame to frame (where fewer than 4 neighbours exist: zero and
        one, the frame's own value, since 3 points or fewer are interpolated exactly and every value is measured
        from the frame's own).
    """
    design = torch.stack([torch.ones_like(offsets), offsets, offsets.square()], dim=-1) * valid[..., None]  # [T,K,3]
    weights = valid[:, :, None].to(values.dtype).expand(*values.shape[:3]).clone()  # [T,K,C]
    ridge = 1e-9 * torch.eye(3, dtype=values.dtype, device=values.device)
    enough = valid.sum(1) >= 4  # [T]
    for robust_pass in range(robust_passes + 1):
        weighted = design[:, :, None, :] * weights[..., None]  # [T,K,C,3]
        normal = torch.einsum("tkca,tkb->tcab", weighted, design) + ridge  # [T,C,3,3]
        moments = torch.einsum("tkca,tkcv->tcav", weighted, values)  # [T,C,3 coefficients,3 components]
        coefficients = torch.linalg.solve(normal, moments)
        if robust_pass == robust_passes:
            break
        fitted = torch.einsum("tka,tcav->tkcv", design, coefficients)
        residual = (values - fitted).norm(dim=-1)  # [T,K,C]
        scale = torch.stack([residual[..., c][valid].median() for c in range(residual.shape[-1])])
        scale = _ROBUST_SCALE * scale.clamp(min=torch.finfo(values.dtype).tiny)
        weights = (1.0 - (residual / scale).square()).clamp(min=0.0).square().clamp(min=1e-3) * valid[..., None]
    # the estimate is sum_k gain_k * value_k: gain_k = weight_k design_k^T normal^-1 e_0
    first = torch.zeros(3, dtype=values.dtype, device=values.device)
    first[0] = 1.0
    centre = torch.linalg.solve(normal, first.expand(*normal.shape[:-1]))  # [T,C,3]
    gains = torch.einsum("tka,tca->tkc", design, centre) * weights
    value = torch.where(enough[:, None, None], coefficients[:, :, 0, :], torch.zeros_like(coefficients[:, :, 0, :]))
    return value, torch.where(enough[:, None], gains.square().sum(1), torch.ones_like(gains[:, 0]))


def smoothing_corrections(bone_transforms: torch.Tensor, heads: torch.Tensor, parents, times: torch.Tensor, *,
                          window: float, robust_passes: int = 2) -> tuple[torch.Tensor, torch.Tensor]:
    """The corrections that bring each frame of a motion to the motion smoothed in time.

    Per-frame estimation noise (a pose estimator's jitter) is mostly independent from frame to frame, while a
    body's motion is smooth over a few frames. Each frame's smoothed pose is a robust local quadratic fit in time
    (Savitzky-Golay's filter where the frames are evenly spaced; any spacing allowed) over the frames within
    ``window`` seconds of it:

    * each joint's rotation relative to its parent is fitted on the rotation manifold, in the tangent space at the
      frame's own rotation (the neighbours' rotations as axis-angle vectors ``log(L_t^T L_s)``), so the value at
      the frame is directly the correction ``d`` of :func:`corrected_transforms` (``L_t exp(d)``);
    * the roots' mean pivot is fitted in the world; the correction moves the roots by the difference.

    A quadratic fit keeps a steady turn and a steady acceleration exactly, also at the ends of the motion and next
    to missing frames, and keeps 70 % of a component varying at 0.5 / ``w`` Hz over a window of half-width ``w``,
    less of faster ones; a frame with fewer than four frames within a window keeps its own pose there (zero
    correction). Where the motion changes faster than that (a kick stopped within a few frames), a wide window
    would round it off by more than the noise: each frame and joint takes the widest of the windows ``window`` x
    (1/6, 1/4, 1/3, 1/2, 2/3, 1) whose estimate agrees with those of all narrower ones (the intersection of
    confidence intervals rule of adaptive local polynomial regression: intervals of +-2.5 standard deviations,
    the noise's level per joint estimated from the residuals at the frames themselves of the narrowest window that
    fits at least half of the frames). A motion with no noise thus keeps its fast moves, and noise is averaged over
    up to ``window`` either side wherever the motion allows.

    Args:
        bone_transforms: [T,J,4,4] the poses, in the order of ``times``.
        heads: [J,3] rest-pose pivots [world units].
        parents: [J] parent index of each joint (-1 for a root).
        times: [T] the frames' times [s], strictly increasing.
        window: the half-width [s] of each frame's neighbourhood; 0 gives zero corrections.
        robust_passes: bisquare reweighting passes after the first fit (see :func:`_local_quadratic_fits`).

    Returns:
        ``(rotation [T,J,3] [rad], translation [T,3] [world units])``, the arguments of
        :func:`corrected_transforms` that give the smoothed poses.
    """
    if not window >= 0:
        raise ValueError(f"window must be non-negative, got {window}")
    poses = torch.as_tensor(bone_transforms, dtype=torch.float64)
    times = torch.as_tensor(times, dtype=torch.float64, device=poses.device)
    heads = torch.as_tensor(heads, dtype=torch.float64, device=poses.device)
    frame_count, joint_count = poses.shape[:2]
    rotation = poses.new_zeros(frame_count, joint_count, 3)
    translation = poses.new_zeros(frame_count, 3)
    if window == 0 or frame_count < 4:
        return rotation, translation
    if bool((times[1:] <= times[:-1]).any()):
        raise ValueError("times must be strictly increasing")
    # each frame's neighbours within the widest window [T,K] (K: the most any frame has), padded with the frame
    margin = 1e-9 * max(1.0, float(times.abs().max()))
    first = torch.searchsorted(times, times - window - margin)
    last = torch.searchsorted(times, times + window + margin, right=True)
    span = int((last - first).max())
    rows = first[:, None] + torch.arange(span, device=poses.device)[None, :]
    valid = rows < last[:, None]
    rows = torch.where(valid, rows, torch.arange(frame_count, device=poses.device)[:, None])
    offsets = (times[rows] - times[:, None]) / window * valid

    local = local_rotations(poses, parents)  # [T,J,3,3]
    relative = axis_angle_from_matrix(local[:, None].transpose(-1, -2) @ local[rows])  # [T,K,J,3]
    roots = torch.as_tensor([int(p) < 0 for p in parents], device=poses.device)
    root_pivots = posed_pivots(poses, heads)[:, roots].mean(1)  # [T,3]
    shifts = root_pivots[rows] - root_pivots[:, None]  # [T,K,3]
    values = torch.cat([relative, shifts[:, :, None]], dim=2)  # [T,K,J+1,3]
    fits = [_local_quadratic_fits(values, offsets / fraction, valid & (offsets.abs() <= fraction + 1e-9),
                                  robust_passes=robust_passes) for fraction in _WINDOW_FRACTIONS]
    fitted = _widest_agreeing(fits)
    return fitted[:, :joint_count], fitted[:, joint_count]


def _widest_agreeing(fits: list[tuple[torch.Tensor, torch.Tensor]]) -> torch.Tensor:
    """Per frame and channel, the estimate [T,C,3] of the widest window whose confidence interval meets those of
    every narrower window (``fits``: :func:`_local_quadratic_fits` of windows from narrowest to widest)."""
    # The noise's variance per channel, from the narrowest window that fits at least half of the frames (a wider
    # one's residuals carry the motion's own curvature where it is fast, which would read as noise and let the
    # widest windows round fast moves off): the fit's residual at the frame itself is minus its estimate, of
    # variance (1 - leverage) per component; the median over the frames is robust to the fastest of them.
    source, source_variance = fits[-1]
    for value, variance in fits:
        if float((variance < 1.0 - 1e-9).float().mean()) >= 0.5:
            source, source_variance = value, variance
            break
    fitted = source_variance < 1.0 - 1e-9  # [T,C] frames with enough neighbours (the others keep their own)
    residual = source.square().sum(-1) / (1.0 - source_variance.clamp(max=0.95))
    noise = torch.stack([residual[:, c][fitted[:, c]].median() if bool(fitted[:, c].any()) else residual.new_zeros(())
                         for c in range(source.shape[1])]) / _CHI2_3_MEDIAN  # [C]
    widest = fits[-1][0]
    low = high = chosen = None
    agree = torch.ones(widest.shape[:2], dtype=torch.bool, device=widest.device)
    for value, variance in fits:
        half = _CONFIDENCE * (noise[None, :] * variance).sqrt()[..., None]
        low = value - half if low is None else torch.maximum(low, value - half)
        high = value + half if high is None else torch.minimum(high, value + half)
        agree = agree & (low <= high).all(-1)
        chosen = value if chosen is None else torch.where(agree[..., None], value, chosen)
    return chosen
