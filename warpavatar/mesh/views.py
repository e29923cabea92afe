"""Renders of the canonical avatar from cameras all around it: what the surface is fused from and the texture
baked from.

The cameras sit on a sphere (a Fibonacci lattice: near-uniform directions, none twice) around the box of the
canonical Gaussians, look at its centre with the world's up kept upright, and frame the whole box. The avatar is
posed at rest (identity bone transforms) through :meth:`warpavatar.model.Avatar.render`, so every part acts as
it does in a fit, and its colours are evaluated at SH degree 0 (the diffuse colour: a texture has no view
direction).

A fit's renders blur every Gaussian by the rasterizer's screen-space 0.3 px^2 (:data:`SCREEN_BLUR_PX2`), without
lowering its opacity, so at the fit's resolution small Gaussians look larger than they are, and the silhouette
the fit matched to its masks is wider than the Gaussians' own (on the demo avatar, at its 64 px frames, the
Gaussians rendered four times finer and box-filtered down reach an IoU of only 0.90 with their own silhouette).
The views can add that blur in 3D (:func:`training_blur`: the same variance, in metres, from the width a training
pixel covers at the subject, less the views' own), so the mesh takes the shape the fit saw.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from warpavatar.kernels.splat import BLUR_EPS2D
from warpavatar.mesh.mesh_data import CanonicalView

DEPTH_ALPHA = 0.5
"""Least alpha of a pixel whose expected depth a view keeps (``inf`` below it)."""

SCREEN_BLUR_PX2 = float(BLUR_EPS2D)
"""Variance [px^2] the Gaussian rasterizer adds to every projected Gaussian (``BLUR_EPS2D`` of
:mod:`warpavatar.kernels.splat`)."""

__all__ = ["DEPTH_ALPHA", "SCREEN_BLUR_PX2", "POSED_FRAMES", "POSED_CAMERAS", "MAX_POSED_VIEW_SIZE",
           "body_gaussians", "canonical_box", "view_cameras", "training_blur", "render_canonical_views",
           "posed_frames", "render_posed_views"]

POSED_FRAMES = 8
"""Frames of the fit's training motion the posed views show (evenly spaced over it)."""

POSED_CAMERAS = 6
"""Cameras around the avatar in each of those frames (all frames' cameras together on one Fibonacci sphere)."""

MAX_POSED_VIEW_SIZE = 1024
"""Largest width and height [px] of a posed view (its pixel is the training pixel where that fits)."""


def body_gaussians(avatar) -> torch.Tensor:
    """[N] bool: the canonical Gaussians that make the body, all but the floaters that ``canonical.ply`` leaves out
    (:func:`warpavatar.fit.outputs.canonical_floaters`: centres far from every bone, or an opacity that changes
    no 8-bit pixel). Only these are rendered and framed, so stray Gaussians neither widen the views' box nor
    become stray geometry."""
    from warpavatar.fit.outputs import canonical_floaters

    gaussians = avatar.gaussians
    with torch.no_grad():
        floaters = canonical_floaters(gaussians.means.detach(), gaussians.opacities.detach(), avatar.skeleton,
                                      scales=gaussians.scales.detach())
    return ~floaters.to(gaussians.means.device)


def canonical_box(avatar, *, quantile: float = 0.002, keep: torch.Tensor | None = None
                  ) -> tuple[np.ndarray, np.ndarray]:
    """(low [3], high [3]) corners [m] of the box of the body's canonical Gaussians (``keep`` [N] bool, by default
    :func:`body_gaussians`): their centres' ``quantile`` and ``1 - quantile`` along each axis (a few stray centres
    do not widen it), padded by three times the median largest scale."""
    gaussians = avatar.gaussians
    keep = body_gaussians(avatar) if keep is None else keep
    with torch.no_grad():
        means = gaussians.means.detach()[keep].float().cpu()
        scales = gaussians.scales.detach()[keep].float().cpu()
    if means.shape[0] == 0:
        raise ValueError("the avatar has no Gaussians near its bones to make a mesh of")
    low = torch.quantile(means, quantile, dim=0) if means.shape[0] > 1 else means[0]
    high = torch.quantile(means, 1.0 - quantile, dim=0) if means.shape[0] > 1 else means[0]
    pad = 3.0 * float(scales.max(dim=1).values.median())
    return (low - pad).numpy().astype(np.float64), (high + pad).numpy().astype(np.float64)


def _look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    forward = target - eye
    forward = forward / np.linalg.norm(forward)
    right = np.cross(forward, up)
    if np.linalg.norm(right) < 1e-6:  # looking along the up axis
        helper = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        right = np.cross(forward, helper)
    right = right / np.linalg.norm(right)
    down = np.cross(forward, right)
    rotation = np.stack([right, down, forward])
    matrix = np.eye(4)
    matrix[:3, :3] = rotation
    matrix[:3, 3] = -rotation @ eye
    return matrix


def view_cameras(low: np.ndarray, high: np.ndarray, up: np.ndarray, *, count: int, size: int,
                 field_of_view_degrees: float = 40.0, indices=None) -> list[tuple[np.ndarray, np.ndarray]]:
    """``count`` cameras ``(K [3,3], world_to_camera [4,4])`` on a Fibonacci sphere around the box ``low``..``high``
    [m], each seeing the whole box in a ``size`` x ``size`` image with the given vertical field of view; with
    ``indices``, only those of the sphere's ``count`` directions, in that order."""
    if count < 1 or size < 8:
        raise ValueError(f"view_cameras: count must be >= 1 and size >= 8, got {count} and {size}")
    up = np.asarray(up, dtype=np.float64)
    up = up / np.linalg.norm(up)
    centre = 0.5 * (low + high)
    radius = 0.5 * float(np.linalg.norm(high - low))
    half = math.radians(field_of_view_degrees) * 0.5
    distance = radius / math.sin(half) * 1.05
    focal = 0.5 * size / math.tan(half)
    K = np.array([[focal, 0.0, (size - 1) * 0.5], [0.0, focal, (size - 1) * 0.5], [0.0, 0.0, 1.0]])
    side = np.cross(up, [1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.cross(up, [0.0, 1.0, 0.0])
    side = side / np.linalg.norm(side)
    other = np.cross(up, side)
    golden = math.pi * (3.0 - math.sqrt(5.0))
    cameras = []
    for index in (range(count) if indices is None else indices):
        height = 1.0 - 2.0 * (index + 0.5) / count  # along up, in -1..1
        ring = math.sqrt(max(0.0, 1.0 - height * height))
        angle = golden * index
        direction = ring * (math.cos(angle) * side + math.sin(angle) * other) + height * up
        cameras.append((K.copy(), _look_at(centre + distance * direction, centre, up)))
    return cameras


def training_blur(training_pixel_size: float | None, view_pixel_size: float = 0.0) -> float:
    """Standard deviation [m] of the isotropic 3D blur that gives views whose pixels are ``view_pixel_size`` [m]
    wide at the subject the fit's screen-space blur (:data:`SCREEN_BLUR_PX2`) at its training pixel width
    ``training_pixel_size`` [m] (:func:`warpavatar.fit.outputs.training_pixel_size`): the views' own screen blur
    is taken off, ``sqrt(SCREEN_BLUR_PX2 * max(training^2 - view^2, 0))``; 0 for None."""
    if training_pixel_size is None:
        return 0.0
    for name, value in (("training", training_pixel_size), ("view", view_pixel_size)):
        if not (math.isfinite(value) and value >= 0.0):
            raise ValueError(f"training_blur: the {name} pixel size must be a non-negative number, got {value}")
    return math.sqrt(SCREEN_BLUR_PX2 * max(float(training_pixel_size) ** 2 - float(view_pixel_size) ** 2, 0.0))


def _body_only(posed, keep: torch.Tensor):
    """The posed Gaussians ``keep`` [N] bool selects (:func:`body_gaussians`): every per-Gaussian entry indexed,
    the rest kept."""
    if bool(keep.all()):
        return posed
    count = int(keep.numel())
    return type(posed)({key: value[keep] if torch.is_tensor(value) and value.dim() > 0 and value.shape[0] == count
                        and key != "bone_transforms" else value for key, value in posed.items()})


def _render_view(avatar, posed, K: np.ndarray, world_to_camera: np.ndarray, size: int) -> CanonicalView:
    """One ``size`` x ``size`` render of the posed Gaussians: colour, alpha and expected depth (``inf`` where alpha
    is below :data:`DEPTH_ALPHA`)."""
    view = CanonicalView(K.astype(np.float32), world_to_camera.astype(np.float32), size, size, None, None, None)
    image, alpha, depth = avatar.rasterize(posed, view)
    alpha = alpha.float().cpu().numpy()
    depth = depth.float().cpu().numpy()
    expected = np.full_like(depth, np.inf)
    covered = alpha >= DEPTH_ALPHA
    expected[covered] = depth[covered] / alpha[covered]
    view.color = image.float().clamp(0.0, 1.0).cpu().numpy()
    view.alpha = alpha
    view.depth = expected
    return view


def render_canonical_views(avatar, *, count: int = 64, size: int = 256, training_pixel_size: float | None = None,
                           device=None) -> list[CanonicalView]:
    """Render the avatar at rest from ``count`` cameras around it (:func:`view_cameras`).

    Args:
        avatar: a :class:`~warpavatar.model.Avatar`.
        count: number of views.
        size: width and height of each image [px].
        training_pixel_size: the width [m] a pixel of the fit's frames covers at the subject: every Gaussian is
            then blurred in 3D (the variance of :func:`training_blur` added to each axis's squared scale, its
            opacity kept) so that the views, their own screen blur included, show the silhouette the fit matched
            to its masks; None: no blur.
        device: where to render (default: the avatar's device).

    Returns:
        the views, with colour at SH degree 0, alpha and expected depth (:class:`CanonicalView`).
    """
    device = avatar.gaussians.means.device if device is None else torch.device(device)
    keep = body_gaussians(avatar)
    low, high = canonical_box(avatar, keep=keep)
    up = np.asarray(avatar.skeleton.up, dtype=np.float64)
    rest = torch.eye(4, device=device).expand(avatar.joint_count, 4, 4).contiguous()
    views = []
    with torch.no_grad():
        posed = avatar.pose(rest, sh_degree=0)
        posed = _body_only(posed, keep)
        cameras = view_cameras(low, high, up, count=count, size=size)
        centre = 0.5 * (low + high)  # every camera sees it at one distance, with one focal length
        view_pixel_size = float(cameras[0][1][2, :3] @ centre + cameras[0][1][2, 3]) / float(cameras[0][0][0, 0])
        blur = training_blur(training_pixel_size, view_pixel_size)
        if blur > 0.0:
            posed["scales"] = torch.sqrt(posed["scales"].square() + blur ** 2)
        for K, world_to_camera in cameras:
            views.append(_render_view(avatar, posed, K, world_to_camera, size))
    return views


def posed_frames(frame_count: int, count: int = POSED_FRAMES) -> np.ndarray:
    """Indices of ``count`` frames evenly spaced over ``frame_count`` (all of them where there are fewer)."""
    if frame_count < 1:
        raise ValueError("posed_frames: the motion has no frames")
    return np.unique(np.linspace(0, frame_count - 1, min(count, frame_count)).round().astype(np.int64))


def render_posed_views(avatar, motion, frames, *, pixel_size: float, cameras: int = POSED_CAMERAS,
                       device=None) -> tuple[list[CanonicalView], np.ndarray]:
    """Render the avatar in some frames of a motion from cameras all around it, each pixel ``pixel_size`` wide at
    the avatar (the fit's training pixel: what the fit's renders looked like to it).

    The ``len(frames) * cameras`` cameras take the directions of one Fibonacci sphere in turn (view ``i`` shows
    frame ``i % len(frames)``), so that over the frames every side is seen; each frames the box of that frame's
    posed body Gaussians (:func:`body_gaussians`).

    Args:
        avatar: a :class:`~warpavatar.model.Avatar`.
        motion: the motion (an :class:`~warpavatar.io.exporters.ExportMotion`); parts with state over time roll
            it out whole first.
        frames: indices of the rows of ``motion`` to show.
        pixel_size: the width [m] of a pixel at the posed box's centre; the views' size follows from it (at most
            :data:`MAX_POSED_VIEW_SIZE`, at least 64 px; where 64 px gives finer pixels, the Gaussians are blurred
            in 3D by :func:`training_blur`, as in :func:`render_canonical_views`).
        cameras: cameras per frame.
        device: where to render (default: the avatar's device).

    Returns:
        ``(views, view_frames)``: the :class:`~warpavatar.mesh.mesh_data.CanonicalView` renders (posed, at SH
        degree 0; ``depth`` the expected camera z) and [N] the index into ``frames`` each view shows.
    """
    if not (math.isfinite(pixel_size) and pixel_size > 0.0):
        raise ValueError(f"render_posed_views: the pixel size must be a positive number of metres, got {pixel_size}")
    device = avatar.gaussians.means.device if device is None else torch.device(device)
    frames = np.asarray(frames, dtype=np.int64).reshape(-1)
    keep = body_gaussians(avatar)
    up = np.asarray(avatar.skeleton.up, dtype=np.float64)
    bones = np.asarray(motion.bone_transforms, dtype=np.float32)
    count = len(frames) * int(cameras)
    half = math.radians(40.0) * 0.5
    with torch.no_grad():
        avatar.prepare_sequence(bones, frame_ids=np.asarray(motion.frame_ids), fps=float(motion.clock_fps))
        posed_frames_ = []
        for t in frames:
            inputs = {name: torch.as_tensor(np.asarray(values)[t], device=device)
                      for name, values in dict(getattr(motion, "part_inputs", {}) or {}).items()}
            posed = avatar.pose(torch.as_tensor(bones[t], device=device), frame_index=int(t), sh_degree=0,
                                inputs=inputs)
            posed_frames_.append(posed)
        boxes = []
        for posed in posed_frames_:
            means = posed["means"][keep].float().cpu()
            if means.shape[0] == 0:
                raise ValueError("the avatar has no Gaussians near its bones to make a mesh of")
            pad = 3.0 * float(posed["scales"][keep].max(dim=1).values.median())
            boxes.append(((torch.quantile(means, 0.002, dim=0) - pad).numpy().astype(np.float64),
                          (torch.quantile(means, 0.998, dim=0) + pad).numpy().astype(np.float64)))
        # one image size for all: the largest box's distance over the pixel, through the 40-degree field of view
        radius = max(0.5 * float(np.linalg.norm(high - low)) for low, high in boxes)
        distance = radius / math.sin(half) * 1.05
        natural = math.ceil(2.0 * math.tan(half) * distance / pixel_size)
        size = int(min(MAX_POSED_VIEW_SIZE, max(64, natural)))
        # where the size is raised to its least, the views' pixels are finer than the training pixel: blur as the
        # canonical views do, so the silhouettes are still the ones the fit saw
        blur = training_blur(pixel_size, distance * 2.0 * math.tan(half) / size) if size > natural else 0.0
        views, view_frames = [], []
        for position, (posed, (low, high)) in enumerate(zip(posed_frames_, boxes)):
            posed = _body_only(posed, keep)
            if blur > 0.0:
                posed["scales"] = torch.sqrt(posed["scales"].square() + blur ** 2)
            indices = range(position, count, len(frames))
            for K, world_to_camera in view_cameras(low, high, up, count=count, size=size, indices=indices):
                views.append(_render_view(avatar, posed, K, world_to_camera, size))
                view_frames.append(position)
    return views, np.asarray(view_frames, dtype=np.int64)
