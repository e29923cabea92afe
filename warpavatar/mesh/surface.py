"""A closed triangle surface fused from renders of the canonical avatar: TSDF fusion with space carving, marching
cubes, floaters dropped, decimated.

The renders (:func:`warpavatar.mesh.views.render_canonical_views`) are fused into a truncated signed distance on a
voxel grid by :func:`warpavatar.ops.integrate_tsdf`: a voxel that any view sees as background is carved empty, so
what remains lies inside every silhouette, and the depths shape it within them (volumetric fusion as in "A
Volumetric Method for Building Complex Models from Range Images", with the carving of "A Theory of Shape by Space
Carving"). The grid is fused twice: coarsely over the region every camera frames, to find the visual hull's box,
then finely over that box. Marching cubes (scikit-image's) on the fine grid, padded with empty voxels, gives a
closed surface; components that are floaters (:data:`FLOATER_AREA_FRACTION`, :data:`FLOATER_BONE_REACH`) or
cavities are dropped, the rest is decimated to the triangle budget by quadric edge collapse (fast-simplification),
and where a collapse pinched two sheets together the sheets are given their own vertices again, so every edge is
between two faces (watertight). Colours fused with the depths become vertex colours.

The voxel is half the renders' pixel footprint at the hull's centre (:data:`VOXELS_PER_PIXEL`: finer would add
voxels, not detail), enlarged where the hull's box would need more than :data:`MAX_VOXELS` (for the demo avatar's
48 renders of 256 px, blurred as at its fit's resolution: 9.4 mm, enlarged to 10.2 mm, about 1/120 of its height),
and the truncation :data:`TRUNCATION_VOXELS` voxels.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import trimesh

from warpavatar.mesh.mesh_data import CanonicalView

__all__ = ["DEFAULT_TRIANGLES", "VOXELS_PER_PIXEL", "MAX_VOXELS", "TRUNCATION_VOXELS", "ALPHA_THRESHOLD",
           "RIM_DEPTH_VOXELS", "SMOOTHING_PASSES", "COARSE_VOXELS", "SPECK_VOXELS", "FLOATER_AREA_FRACTION",
           "FLOATER_BONE_REACH", "SILHOUETTE_ROUNDS", "CONTOUR_COSINE", "SMOOTHING_RINGS",
           "default_voxel_size", "fuse_views", "depth_offset", "fit_silhouettes", "extract_surface"]

DEFAULT_TRIANGLES = 50_000
"""Triangles of the decimated surface."""

VOXELS_PER_PIXEL = 2.0
"""Default voxel size: the renders' median pixel footprint at the hull's centre [m] divided by this (finer voxels
than pixels place the surface between pixel centres, from the depths' expected values)."""

MAX_VOXELS = 8_000_000
"""Most voxels of the fine grid by default: a larger voxel is taken where the default one would need more
(memory, time; ``max_voxels`` of :func:`extract_surface` changes it)."""

TRUNCATION_VOXELS = 5.0
"""Truncation of the signed distance, in voxels: a view's distance counts up to this far behind its depth. It also
bounds :func:`depth_offset` (at one voxel less): with renders blurred as at the fit's resolution, 5 gave the demo
avatar's mesh its best silhouette IoU against the Gaussians on the training frames (0.958; 4: 0.951, 6: 0.957)."""

ALPHA_THRESHOLD = 0.5
"""Pixels with less alpha are background (carve); the renders' depth is ``inf`` there."""

RIM_DEPTH_VOXELS = 1.0
"""How deep [voxels] inside the silhouettes' surface the carved hull's rim voxels lie, for :func:`depth_offset`:
the surface is between a rim voxel and its carved neighbour, and the hull of many views lies a little inside
each one's silhouette (1.0 matched the silhouettes of the demo avatar's renders best: 0.5 to 2.5 were tried)."""

SMOOTHING_PASSES = 1
"""Passes of a [1, 2, 1] / 4 filter along each axis over the fused distances before marching cubes (a Gaussian of
about 0.7 voxels: the depths of soft Gaussians are noisy from view to view; on the demo avatar one pass costs 0.005
of silhouette IoU and takes off most of the voxel-sized bumps)."""

COARSE_VOXELS = 64
"""Voxels along each axis of the coarse pass (the cube every camera frames)."""

SPECK_VOXELS = 8.0
"""A component enclosing less than this many voxels' volume is dropped (a speck of the fusion's noise)."""

FLOATER_AREA_FRACTION = 0.25
"""A component whose area is below this fraction of the largest component's is a floater candidate."""

FLOATER_BONE_REACH = 0.1
"""A floater candidate is dropped when no vertex of it is within this fraction of the skeleton's height (its
joints' extent along its up axis) of a bone segment; without a skeleton, every candidate is dropped."""

SILHOUETTE_ROUNDS = 8
"""Rounds of :func:`fit_silhouettes` (each moves a vertex at most one voxel along its normal)."""

CONTOUR_COSINE = 0.5
"""How squarely a view must see a vertex's silhouette edge for :func:`fit_silhouettes`: a view's weight is
``1 - |cos| / CONTOUR_COSINE`` (none above it), with ``cos`` the cosine between the vertex's normal and the view's
ray (a normal across the ray moves the edge the most)."""

SMOOTHING_RINGS = 2
"""Rings of neighbours each vertex's move in :func:`fit_silhouettes` is averaged over (a view's edge is known to
about a pixel, a vertex sees few views on its contour)."""


def _stack_views(views: list[CanonicalView], device: torch.device) -> dict[str, torch.Tensor]:
    if not views:
        raise ValueError("extract_surface: no views to fuse")
    sizes = {(int(view.width), int(view.height)) for view in views}
    if len(sizes) != 1:
        raise ValueError(f"extract_surface: the views must share one image size, got {sorted(sizes)}")
    width, height = sizes.pop()
    for index, view in enumerate(views):
        for name in ("color", "alpha", "depth"):
            if getattr(view, name) is None:
                raise ValueError(f"extract_surface: view {index} has no {name} (render it first)")
        if view.alpha.shape != (height, width) or view.depth.shape != (height, width) \
                or view.color.shape != (height, width, 3):
            raise ValueError(f"extract_surface: view {index} holds images of the wrong shape for {width}x{height}")

    def stack(name, dtype=np.float32):
        stacked = np.ascontiguousarray(np.stack([getattr(view, name) for view in views]), dtype=dtype)
        return torch.from_numpy(stacked).to(device)

    return {"depth": stack("depth"), "alpha": stack("alpha"), "color": stack("color"), "K": stack("K"),
            "world_to_camera": stack("world_to_camera")}


def _framed_cube(views: list[CanonicalView]) -> tuple[np.ndarray, float]:
    """(centre [3], half side [m]) of a cube around the point the cameras look at, as large as the smallest sphere
    around it that a view frames whole (its corners may fall outside some images: they stay unknown there)."""
    rotations = np.stack([np.asarray(v.world_to_camera, np.float64)[:3, :3] for v in views])
    eyes = np.stack([-r.T @ np.asarray(v.world_to_camera, np.float64)[:3, 3] for r, v in zip(rotations, views)])
    axes = rotations[:, 2]  # each camera's optical axis in the world
    # least-squares point closest to every optical axis: sum (I - a a^T) (c - eye) = 0
    projectors = np.eye(3)[None] - axes[:, :, None] * axes[:, None, :]
    system = projectors.sum(0)
    if np.linalg.cond(system) > 1e8:  # every camera along one axis: the point halfway along the first's depths
        finite = np.isfinite(views[0].depth)
        reach = float(np.median(views[0].depth[finite])) if finite.any() else 1.0
        centre = eyes[0] + reach * axes[0]
    else:
        centre = np.linalg.solve(system, np.einsum("vij,vj->i", projectors, eyes))
    radius = math.inf
    for view, eye, axis in zip(views, eyes, axes):
        K = np.asarray(view.K, np.float64)
        distance = float(np.linalg.norm(centre - eye))
        half_x = math.atan(min(K[0, 2] + 0.5, view.width - 0.5 - K[0, 2]) / K[0, 0])
        half_y = math.atan(min(K[1, 2] + 0.5, view.height - 0.5 - K[1, 2]) / K[1, 1])
        off_axis = math.acos(min(1.0, max(-1.0, float(axis @ (centre - eye)) / max(distance, 1e-12))))
        radius = min(radius, distance * math.sin(max(0.0, min(half_x, half_y) - off_axis)))
    if not radius > 0.0:
        raise ValueError("extract_surface: the views do not all look at one region")
    return centre, radius


def _pixel_footprint(views: list[CanonicalView], point: np.ndarray) -> float:
    """Median over the views of the width [m] one pixel covers at ``point``."""
    footprints = []
    for view in views:
        matrix = np.asarray(view.world_to_camera, np.float64)
        z = float(matrix[2, :3] @ point + matrix[2, 3])
        focal = math.sqrt(float(view.K[0, 0]) * float(view.K[1, 1]))
        if z > 0.0:
            footprints.append(z / focal)
    if not footprints:
        raise ValueError("extract_surface: the region to fuse is behind every camera")
    return float(np.median(footprints))


def default_voxel_size(views: list[CanonicalView], low: np.ndarray, high: np.ndarray, *,
                       max_voxels: int = MAX_VOXELS) -> float:
    """The fine grid's voxel size [m] over the box ``low``..``high``: the renders' median pixel footprint at the
    box's centre over :data:`VOXELS_PER_PIXEL`, enlarged where the box would need more than ``max_voxels``."""
    if int(max_voxels) < 1:
        raise ValueError(f"extract_surface: max_voxels must be at least 1, got {max_voxels}")
    size = _pixel_footprint(views, 0.5 * (low + high)) / VOXELS_PER_PIXEL
    volume = float(np.prod(np.maximum(high - low, 1e-9)))
    return max(size, (volume / int(max_voxels)) ** (1.0 / 3.0))


def fuse_views(views, low, high, voxel_size: float, *, truncation: float | None = None,
               device=None) -> dict[str, np.ndarray]:
    """Fuse views into a TSDF on a grid of voxel centres covering the box ``low``..``high`` [m].

    Args:
        views: renders with colour, alpha and depth, all of one size (or the dict ``_stack_views`` makes of
            them, on the device).
        low, high: [3] corners of the box [m]; the first voxel centre is ``low``.
        voxel_size: spacing of the voxel centres [m].
        truncation: [m]; default :data:`TRUNCATION_VOXELS` voxels.
        device: where to run the kernel (default CPU).

    Returns:
        ``{"tsdf": [X,Y,Z], "weight": [X,Y,Z], "color": [X,Y,Z,3], "origin": [3], "voxel_size": float,
        "truncation": float}``, numpy float32 (see :func:`warpavatar.ops.integrate_tsdf`).
    """
    from warpavatar import ops

    device = torch.device("cpu" if device is None else device)
    low, high = np.asarray(low, np.float64), np.asarray(high, np.float64)
    truncation = TRUNCATION_VOXELS * voxel_size if truncation is None else float(truncation)
    shape = tuple(int(n) for n in np.floor((high - low) / voxel_size + 1e-6).astype(np.int64) + 1)
    stacked = views if isinstance(views, dict) else _stack_views(views, device)
    with torch.no_grad():
        tsdf, weight, color = ops.integrate_tsdf(
            stacked["depth"], stacked["alpha"], stacked["color"], stacked["K"], stacked["world_to_camera"],
            tuple(low), voxel_size, shape, truncation=truncation, alpha_threshold=ALPHA_THRESHOLD)
    return {"tsdf": tsdf.cpu().numpy(), "weight": weight.cpu().numpy(), "color": color.cpu().numpy(),
            "origin": low.astype(np.float32), "voxel_size": float(voxel_size), "truncation": truncation}


def _hull_box(views: list[CanonicalView], device, stacked: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The box [m] of the views' visual hull (voxels of the coarse pass left inside), two coarse voxels wider."""
    centre, radius = _framed_cube(views)
    coarse = 2.0 * radius / (COARSE_VOXELS - 1)
    grid = fuse_views(views if stacked is None else stacked, centre - radius, centre + radius, coarse, device=device)
    inside = np.argwhere(grid["tsdf"] < 0.0)
    if inside.shape[0] == 0:
        raise ValueError("extract_surface: the views show nothing to make a surface of (every voxel is carved)")
    low = centre - radius + coarse * (inside.min(0) - 2)
    high = centre - radius + coarse * (inside.max(0) + 2)
    return low, high


def _carved_neighbours(carved: np.ndarray) -> np.ndarray:
    """[X,Y,Z] bool: voxels with a carved voxel among their six face neighbours."""
    near = np.zeros_like(carved)
    for axis in range(3):
        ahead = [slice(None)] * 3
        behind = [slice(None)] * 3
        ahead[axis], behind[axis] = slice(1, None), slice(None, -1)
        near[tuple(behind)] |= carved[tuple(ahead)]
        near[tuple(ahead)] |= carved[tuple(behind)]
    return near


def depth_offset(grid: dict) -> float:
    """How far [m] the views' depths lie behind the surface their silhouettes show, from the fused grid.

    The renders' depth is the alpha-weighted mean depth along each ray; through the soft edges of Gaussians that
    mean lies behind where alpha reaches one half (the silhouettes' surface) by about a Gaussian's size. The rim
    of the carved hull (voxels fused from the depths with a carved face neighbour) is where the silhouettes put
    the surface, just outside the rim voxels' centres: the offset is the rim's median signed distance plus
    :data:`RIM_DEPTH_VOXELS` voxels, within 0 .. truncation - one voxel (0 when no rim voxel was fused).
    """
    voxel, truncation = grid["voxel_size"], grid["truncation"]
    carved = (grid["weight"] == 0.0) & (grid["tsdf"] > 0.0)
    rim = ~carved & (grid["weight"] > 0.0) & _carved_neighbours(carved)
    if not rim.any():
        return 0.0
    offset = float(np.median(grid["tsdf"][rim])) + RIM_DEPTH_VOXELS * voxel
    return min(max(offset, 0.0), max(truncation - voxel, 0.0))


def _smoothed(values: np.ndarray, passes: int) -> np.ndarray:
    """``values`` [X,Y,Z] filtered ``passes`` times by [1, 2, 1] / 4 along each axis (edges repeated)."""
    for _ in range(passes):
        for axis in range(3):
            padded = np.pad(values, [(1, 1) if a == axis else (0, 0) for a in range(3)], mode="edge")
            part = [slice(None)] * 3
            shifted = []
            for start in range(3):
                part[axis] = slice(start, start + values.shape[axis])
                shifted.append(padded[tuple(part)])
            values = 0.25 * shifted[0] + 0.5 * shifted[1] + 0.25 * shifted[2]
    return values


def _marching_cubes(grid: dict, *, offset: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Vertices [m] and outward-wound faces of the TSDF's level ``offset`` (the fused distances are moved by it:
    :func:`depth_offset`), smoothed (:data:`SMOOTHING_PASSES`), the grid padded with empty voxels so the surface
    closes at its border."""
    from skimage.measure import marching_cubes

    tsdf = grid["tsdf"]
    voxel = grid["voxel_size"]
    fused = grid["weight"] > 0.0
    # Carved voxels hold +truncation; next to an inside voxel that would pull the zero crossing inwards by up to
    # the truncation's share. A carved voxel's centre is just outside a silhouette: half a voxel is its distance.
    values = np.where(fused, tsdf - np.float32(offset), tsdf)
    values = np.where(~fused & (tsdf > 0.0), np.float32(min(0.5 * voxel, grid["truncation"])), values)
    values = _smoothed(values, SMOOTHING_PASSES).astype(np.float32)
    values = np.pad(values, 1, mode="constant", constant_values=np.float32(grid["truncation"]))
    values[values == 0.0] = np.float32(1e-7 * voxel)  # no vertex exactly on a voxel centre (degenerate faces)
    if not (values.min() < 0.0 < values.max()):
        return np.zeros((0, 3), np.float64), np.zeros((0, 3), np.int64)
    vertices, faces, _, _ = marching_cubes(values, level=0.0, spacing=(voxel, voxel, voxel),
                                           gradient_direction="descent", allow_degenerate=False)
    vertices = vertices.astype(np.float64) + (grid["origin"].astype(np.float64) - voxel)
    return vertices, faces.astype(np.int64)


def _bone_segments(skeleton) -> tuple[np.ndarray, np.ndarray, float] | None:
    if skeleton is None:
        return None
    heads = np.asarray(skeleton.heads, np.float64)
    tails = np.asarray(skeleton.tails, np.float64)
    up = np.asarray(skeleton.up, np.float64)
    up = up / max(np.linalg.norm(up), 1e-12)
    heights = np.concatenate([heads, tails]) @ up
    return heads, tails, float(heights.max() - heights.min())


def _distance_to_bones(points: np.ndarray, heads: np.ndarray, tails: np.ndarray) -> float:
    """Smallest distance [m] from any of ``points`` [N,3] to any bone segment."""
    directions = tails - heads
    lengths = np.maximum((directions * directions).sum(-1), 1e-12)
    best = math.inf
    for start in range(0, points.shape[0], 4096):
        chunk = points[start:start + 4096]
        along = np.clip(((chunk[:, None] - heads[None]) * directions[None]).sum(-1) / lengths[None], 0.0, 1.0)
        nearest = heads[None] + along[..., None] * directions[None]
        best = min(best, float(np.sqrt(((chunk[:, None] - nearest) ** 2).sum(-1).min())))
    return best


def _component_labels(faces: np.ndarray) -> np.ndarray:
    """[F] int64 label of each face's connected component (faces joined through shared edges)."""
    if faces.shape[0] == 0:
        return np.zeros(0, np.int64)
    adjacency = trimesh.graph.face_adjacency(faces=faces)
    return np.asarray(trimesh.graph.connected_component_labels(adjacency, node_count=faces.shape[0]), np.int64)


def _kept_components(vertices: np.ndarray, faces: np.ndarray, skeleton, voxel_size: float) -> np.ndarray:
    """[F] bool: faces of the components kept (the rule in :func:`extract_surface`)."""
    labels = _component_labels(faces)
    if labels.shape[0] == 0:
        return np.zeros(0, dtype=bool)
    corners = vertices[faces]
    crossed = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    areas = np.bincount(labels, weights=0.5 * np.linalg.norm(crossed, axis=1))
    volumes = np.bincount(labels, weights=(corners[:, 0] * crossed).sum(1) / 6.0)
    # A component wound inwards (negative volume) is the wall of a cavity, unseen from outside; one enclosing
    # less than a few voxels is a speck (decimation would crush it flat).
    keep = volumes > SPECK_VOXELS * voxel_size ** 3
    if not keep.any():
        return np.zeros(faces.shape[0], dtype=bool)
    largest = float(areas[keep].max())
    bones = _bone_segments(skeleton)
    for component in np.flatnonzero(keep & (areas < FLOATER_AREA_FRACTION * largest)):
        if bones is None:
            keep[component] = False
            continue
        heads, tails, height = bones
        component_vertices = vertices[np.unique(faces[labels == component])]
        keep[component] = _distance_to_bones(component_vertices, heads, tails) <= FLOATER_BONE_REACH * height
    return keep[labels]


def _compacted(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The vertices the faces use, and the faces renumbered to them."""
    used, inverse = np.unique(faces.reshape(-1), return_inverse=True)
    return vertices[used], inverse.reshape(faces.shape).astype(np.int64)


def _edge_partners(vertices: np.ndarray, faces: np.ndarray, *, turned: np.ndarray | None = None) -> np.ndarray:
    """[3F] the half-edge across from each half-edge (half-edge ``3 f + k`` runs from corner k of face f to
    corner k + 1), -1 where none.

    An edge of two faces pairs them. Around an edge of more (two sheets touching where a collapse pinched them),
    the faces are sorted by angle about the edge; a face's outward normal points towards increasing angle when
    its half-edge runs along the edge's axis, so it pairs with its neighbour at decreasing angle (the wedge
    between them is solid), and a face running against the axis with its neighbour at increasing angle. Edges
    whose half-edges ``turned`` (a [3F] bool, or None) marks pair the other way round (each face with its other
    neighbour: the pairing that separates a fan which meets itself along the edge). Where the faces do not
    alternate in direction around the edge (a fold that crosses itself), those along the axis pair with those
    against it in angular order (shifted by one where ``turned``).
    """
    half_from = faces.reshape(-1)
    half_to = np.roll(faces, -1, axis=1).reshape(-1)
    low, high = np.minimum(half_from, half_to), np.maximum(half_from, half_to)
    key = low * np.int64(vertices.shape[0]) + high
    order = np.argsort(key, kind="stable")
    ordered = key[order]
    starts = np.flatnonzero(np.r_[True, ordered[1:] != ordered[:-1]])
    counts = np.diff(np.r_[starts, key.shape[0]])
    partner = np.full(key.shape[0], -1, np.int64)
    pairs = starts[counts == 2]
    first, second = order[pairs], order[pairs + 1]
    opposite = half_from[first] == half_to[second]  # consistently wound: the two run in opposite directions
    partner[first[opposite]], partner[second[opposite]] = second[opposite], first[opposite]
    for start, count in zip(starts[counts > 2], counts[counts > 2]):
        halves = order[start:start + count]
        a, b = low[halves[0]], high[halves[0]]
        axis = vertices[b] - vertices[a]
        axis = axis / max(np.linalg.norm(axis), 1e-30)
        helper = np.eye(3)[int(np.argmin(np.abs(axis)))]
        e1 = np.cross(axis, helper)
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(axis, e1)
        third = faces[halves // 3, (halves % 3 + 2) % 3]
        spoke = vertices[third] - vertices[a]
        angles = np.arctan2(spoke @ e2, spoke @ e1)
        around = halves[np.argsort(angles)]
        forward = half_from[around] == a
        turn = turned is not None and bool(turned[halves].any())
        if np.all(forward != np.roll(forward, 1)):
            for position, half in enumerate(around):
                partner[half] = around[(position + (-1 if forward[position] != turn else 1)) % count]
        elif 2 * int(forward.sum()) == count:  # folded over itself (not alternating): any pairing closes it
            along, against = around[forward], np.roll(around[~forward], -int(turn))
            partner[along], partner[against] = against, along
    mutual = partner >= 0
    mutual[mutual] = partner[partner[mutual]] == np.flatnonzero(mutual)
    partner[~mutual] = -1
    return partner


MANIFOLD_ROUNDS = 4
"""Pairings tried by :func:`_manifold` before it keeps the one with the fewest edges of more than two faces."""


def _without_folds(faces: np.ndarray) -> np.ndarray:
    """The faces less each pair of one triangle wound both ways (a fold of zero volume that decimation leaves;
    every edge loses one use in each direction, so what was closed stays closed)."""
    if faces.shape[0] == 0:
        return faces
    key = np.sort(faces, axis=1)
    # a triangle's winding: even or odd permutation of its sorted corners
    smallest = np.argmin(faces, axis=1)
    rolled = np.take_along_axis(faces, (smallest[:, None] + np.arange(3)[None]) % 3, axis=1)
    parity = (rolled[:, 1] > rolled[:, 2]).astype(np.int64)
    _, group = np.unique(key, axis=0, return_inverse=True)
    group = group.reshape(-1)
    drop = np.zeros(faces.shape[0], dtype=bool)
    order = np.lexsort((parity, group))
    ordered_group, ordered_parity = group[order], parity[order]
    starts = np.flatnonzero(np.r_[True, ordered_group[1:] != ordered_group[:-1]])
    for start, stop in zip(starts, np.r_[starts[1:], order.shape[0]]):
        if stop - start < 2:
            continue
        members = order[start:stop]
        even, odd = members[ordered_parity[start:stop] == 0], members[ordered_parity[start:stop] == 1]
        pairs = min(even.shape[0], odd.shape[0])
        drop[even[:pairs]] = True
        drop[odd[:pairs]] = True
    return faces[~drop]


def _split_fans(vertices: np.ndarray, faces: np.ndarray, partner: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each vertex split into one copy per fan of faces around it that the half-edge pairs ``partner`` join."""
    halves = np.flatnonzero(partner >= 0)
    others = partner[halves]
    face, corner = halves // 3, halves % 3
    other_face, other_corner = others // 3, others % 3
    # half-edge (f, k) runs v0 -> v1 and its partner (g, l) v1 -> v0: corner k of f and corner l + 1 of g are
    # v0, corner k + 1 of f and corner l of g are v1
    links = np.concatenate([
        np.stack([3 * face + corner, 3 * other_face + (other_corner + 1) % 3], axis=1),
        np.stack([3 * face + (corner + 1) % 3, 3 * other_face + other_corner], axis=1)])
    # corners of one vertex that no pair joins stay apart; corners of different vertices are never linked
    labels = np.asarray(trimesh.graph.connected_component_labels(links, node_count=3 * faces.shape[0]), np.int64)
    _, first_corner, new_faces = np.unique(labels, return_index=True, return_inverse=True)
    return vertices[faces.reshape(-1)[first_corner]], new_faces.reshape(faces.shape).astype(np.int64)


def _crowded_halves(faces: np.ndarray) -> np.ndarray:
    """[3F] bool: half-edges on an edge of more than two faces."""
    half_from, half_to = faces.reshape(-1), np.roll(faces, -1, axis=1).reshape(-1)
    key = np.minimum(half_from, half_to) * np.int64(max(int(faces.max()) + 1, 1)) + np.maximum(half_from, half_to)
    _, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
    return counts[inverse.reshape(-1)] > 2


def _manifold(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The mesh with every edge between exactly two faces where it can be: faces paired across each edge
    (:func:`_edge_partners`) and each vertex split into one copy per fan of faces around it that those pairs
    join (a pinch becomes two coincident vertices, each on its own sheet). Where an edge still has more than two
    faces (a fan that meets itself along it), its faces are paired the other way round and the split redone, up
    to :data:`MANIFOLD_ROUNDS` times in all."""
    if faces.shape[0] == 0:
        return vertices, faces
    turned = np.zeros(3 * faces.shape[0], dtype=bool)
    best = None
    for _ in range(MANIFOLD_ROUNDS):
        split_vertices, split_faces = _split_fans(vertices, faces, _edge_partners(vertices, faces, turned=turned))
        crowded = _crowded_halves(split_faces)
        if best is None or crowded.sum() < best[0]:
            best = (int(crowded.sum()), split_vertices, split_faces)
        if not crowded.any():
            break
        turned ^= crowded
    return best[1], best[2]


def _decimated(vertices: np.ndarray, faces: np.ndarray, triangles: int) -> tuple[np.ndarray, np.ndarray]:
    import fast_simplification

    for _ in range(3):  # a pass may stop short of its target: the next goes on from where it stopped
        if faces.shape[0] <= triangles:
            break
        vertices, faces = fast_simplification.simplify(vertices, faces, target_count=triangles)
        vertices, faces = np.asarray(vertices, np.float64), np.asarray(faces, np.int64)
    return vertices, faces


def _silhouette_fields(alpha: torch.Tensor) -> torch.Tensor:
    """[N,H,W] signed distance [px] from each pixel centre to its view's silhouette edge (alpha at
    :data:`ALPHA_THRESHOLD`), positive outside: exact distance transforms of the thresholded alpha, so that
    interpolated between the two pixels either side of the edge it crosses zero half-way."""
    from scipy import ndimage

    fields = []
    for image in alpha.detach().cpu().numpy():
        inside = image >= ALPHA_THRESHOLD
        far = float(sum(image.shape))
        if inside.all() or not inside.any():
            fields.append(np.full(image.shape, -far if inside.all() else far))
            continue
        fields.append(np.where(inside, 0.5 - ndimage.distance_transform_edt(inside),
                               ndimage.distance_transform_edt(~inside) - 0.5))
    return torch.from_numpy(np.stack(fields).astype(np.float32)).to(alpha.device)


def _edge_distances(field: torch.Tensor, alpha: torch.Tensor, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """[N,V] signed distance [px] from the points ``(u, v)`` [N,V] (pixel coordinates) to each view's silhouette
    edge: within a pixel and a half of the edge, where the alpha ramps, the distance of the interpolated alpha to
    :data:`ALPHA_THRESHOLD` over its slope there (a soft edge placed between pixel centres), else the
    interpolated distance field (:func:`_silhouette_fields`)."""
    height, width = field.shape[-2:]

    def sample(image: torch.Tensor, du: float = 0.0, dv: float = 0.0) -> torch.Tensor:
        grid = torch.stack([(u + du) / max(width - 1, 1) * 2.0 - 1.0, (v + dv) / max(height - 1, 1) * 2.0 - 1.0],
                           dim=-1)[:, None]
        return torch.nn.functional.grid_sample(image, grid, align_corners=True, padding_mode="border")[:, 0, 0]

    distance = sample(field)
    value = sample(alpha)
    slope = torch.hypot(sample(alpha, 0.5) - sample(alpha, -0.5), sample(alpha, 0.0, 0.5) - sample(alpha, 0.0, -0.5))
    crossing = (ALPHA_THRESHOLD - value) / slope.clamp_min(1e-6)
    ramp = (distance.abs() <= 2.0) & (slope > 0.05) & (crossing.abs() <= 1.5)
    return torch.where(ramp, crossing, distance)


def _torch_vertex_normals(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    corners = vertices[faces]
    face_normals = torch.linalg.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normals = torch.zeros_like(vertices)
    for corner in range(3):
        normals.index_add_(0, faces[:, corner], face_normals)
    return normals / normals.norm(dim=1, keepdim=True).clamp_min(1e-30)


def _mesh_silhouettes(points: torch.Tensor, faces: torch.Tensor, K: torch.Tensor, matrices: torch.Tensor,
                      width: int, height: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``(alpha [N,H,W], depth [N,H,W])`` of the mesh ray cast through each view, with view ``n`` seeing the
    vertices at ``points[n]`` [N,V,3] (:func:`warpavatar.ops.render_mesh`: 1 where a face is hit, its camera z
    there, 0 elsewhere)."""
    from warpavatar import ops

    alphas, depths = [], []
    for index in range(K.shape[0]):
        _, alpha, depth = ops.render_mesh(points[index].contiguous(), faces, K[index], matrices[index], width, height)
        alphas.append(alpha)
        depths.append(depth)
    return torch.stack(alphas), torch.stack(depths)


def fit_silhouettes(vertices: np.ndarray, faces: np.ndarray, views, *, voxel_size: float,
                    rounds: int = SILHOUETTE_ROUNDS, poses: torch.Tensor | None = None,
                    view_poses: torch.Tensor | None = None, device=None) -> np.ndarray:
    """The surface's vertices moved along their normals until its silhouettes match the views'.

    The fused level set is placed by one depth offset for the whole grid (:func:`depth_offset`), so where the
    Gaussians' soft edges are wider or narrower than the median, the surface is too wide or too thin there. Each
    round ray casts the surface through every view and compares the two silhouettes where the surface's edge is:
    at every vertex within two pixels of the surface's own silhouette edge, not hidden behind nearer surface and
    with its normal across the ray (:data:`CONTOUR_COSINE`), the view's signed distance to its silhouette edge
    (:func:`_edge_distances`) less the surface's (both in pixels; their difference, in metres at the vertex's
    depth, is how far the surface's edge lies outside the view's there, whatever bumps of the surface make that
    edge). The moves are averaged over the views, weighted by how squarely each sees the edge, smoothed over the
    vertex's neighbours (:data:`SMOOTHING_RINGS`) and capped at one voxel a round, along the fused surface's
    normals, which stay fixed.

    Args:
        vertices: [V,3] [m]; faces: [F,3] counter-clockwise seen from outside.
        views: the renders (:class:`~warpavatar.mesh.mesh_data.CanonicalView`) or the dict ``_stack_views``
            makes of them.
        voxel_size: the fused grid's voxel [m]: the largest move a round, and the scale of the band a view's
            difference is trusted within (six voxels either way).
        rounds: how many rounds.
        poses: [P,V,3,4] per-vertex affine maps from the vertices' frame to the views' world (skinning: a vertex
            ``x`` is seen at ``A x + b``, with ``[A | b]`` its pose), or None: the views see the vertices as given.
        view_poses: [N] index into ``poses`` of each view's pose (with ``poses``).
        device: where to compute (default CPU).

    Returns:
        [V,3] float64 moved vertices (the faces are unchanged: the surface stays closed).
    """
    device = torch.device("cpu" if device is None else device)
    stacked = views if isinstance(views, dict) else _stack_views(views, device)
    if faces.shape[0] == 0 or rounds < 1:
        return np.asarray(vertices, np.float64)
    alpha = stacked["alpha"].to(device, torch.float32)
    field = _silhouette_fields(alpha)[:, None]
    alpha = alpha[:, None]
    K = stacked["K"].to(device, torch.float32)
    matrices = stacked["world_to_camera"].to(device, torch.float32)
    rotation, translation = matrices[:, :3, :3], matrices[:, :3, 3]
    eyes = -torch.einsum("nji,nj->ni", rotation, translation)
    height, width = field.shape[-2:]
    focal = torch.sqrt(K[:, 0, 0] * K[:, 1, 1])[:, None]
    points = torch.as_tensor(np.asarray(vertices), dtype=torch.float32, device=device).clone()
    face_index = torch.as_tensor(np.asarray(faces), dtype=torch.long, device=device)
    edges = torch.cat([face_index[:, [0, 1]], face_index[:, [1, 2]], face_index[:, [2, 0]]])
    edges = torch.cat([edges, edges.flip(1)])
    voxel = float(voxel_size)
    band, occlusion = 6.0 * voxel, TRUNCATION_VOXELS * voxel

    def spread(values: torch.Tensor) -> torch.Tensor:  # each vertex's value plus its neighbours'
        return values.index_add(0, edges[:, 0], values[edges[:, 1]])

    def sample(image: torch.Tensor, grid: torch.Tensor, mode: str = "bilinear") -> torch.Tensor:
        return torch.nn.functional.grid_sample(image, grid, mode=mode, align_corners=True,
                                               padding_mode="border")[:, 0, 0]

    # the moves are along the surface's normals as fused (smoothed once over the neighbours), which stay fixed: a
    # move per vertex that the rounds refine, not a surface whose own bumps steer it
    start = points.clone()
    normals = spread(_torch_vertex_normals(points, face_index))
    normals = normals / normals.norm(dim=1, keepdim=True).clamp_min(1e-30)
    offsets = torch.zeros(points.shape[0], device=device)
    if poses is not None:
        poses = poses.to(device, torch.float32)
        view_poses = torch.as_tensor(view_poses, dtype=torch.long, device=device)
        if view_poses.shape != (K.shape[0],) or poses.shape[1:] != (points.shape[0], 3, 4):
            raise ValueError("fit_silhouettes: poses must be [P,V,3,4] and view_poses hold one index a view")
    for _ in range(int(rounds)):
        points = start + normals * offsets[:, None]
        if poses is None:
            seen_points, seen_normals = points[None].expand(K.shape[0], -1, -1), normals[None]
        else:  # every view's world: the pose's affine map of the vertices and (near-rigid) of their normals
            posed = torch.einsum("pvij,vj->pvi", poses[..., :3], points) + poses[..., 3]
            turned = torch.einsum("pvij,vj->pvi", poses[..., :3], normals)
            seen_points = posed[view_poses]
            seen_normals = (turned / turned.norm(dim=-1, keepdim=True).clamp_min(1e-12))[view_poses]
        mesh_alpha, mesh_depth = _mesh_silhouettes(seen_points, face_index, K, matrices, int(width), int(height))
        mesh_field = _silhouette_fields(mesh_alpha)[:, None]
        camera = torch.einsum("nij,nvj->nvi", rotation, seen_points) + translation[:, None]
        z = camera[..., 2]
        safe_z = z.clamp_min(1e-6)
        u = K[:, 0, 0, None] * camera[..., 0] / safe_z + K[:, 0, 2, None]
        v = K[:, 1, 1, None] * camera[..., 1] / safe_z + K[:, 1, 2, None]
        grid = torch.stack([u / max(width - 1, 1) * 2.0 - 1.0, v / max(height - 1, 1) * 2.0 - 1.0], dim=-1)[:, None]
        own = sample(mesh_field, grid)
        seen = sample(mesh_depth[:, None], grid, mode="nearest")
        metres = (_edge_distances(field, alpha, u, v) - own) * z / focal
        rays = seen_points - eyes[:, None]
        rays = rays / rays.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        cosine = (rays * seen_normals).sum(-1)
        weight = (1.0 - cosine.abs() / CONTOUR_COSINE).clamp_min(0.0)
        in_frame = (z > 0.0) & (u >= 0.0) & (u <= width - 1) & (v >= 0.0) & (v <= height - 1)
        visible = (seen <= 0.0) | (seen > z - occlusion)  # nothing hit there, or nothing well in front
        weight = weight * (in_frame & visible & (own.abs() <= 2.0) & (metres.abs() <= band))
        sine = (1.0 - cosine.square()).clamp_min(0.25).sqrt()
        move, confidence = -(weight * metres / sine).sum(0), weight.sum(0)
        for _ in range(SMOOTHING_RINGS):
            move, confidence = spread(move), spread(confidence)
        step = torch.where(confidence > 1e-3, move / confidence.clamp_min(1e-3), torch.zeros_like(move))
        offsets = offsets + step.clamp(-voxel, voxel)
    points = start + normals * offsets[:, None]
    return points.double().cpu().numpy()


def _sample_colors(grid: dict, points: np.ndarray) -> np.ndarray:
    """[N,3] uint8 colours of the fused grid at ``points`` [m]: trilinear over the voxels that views averaged."""
    weight = (grid["weight"] > 0.0).astype(np.float32)
    color = grid["color"] * weight[..., None]
    shape = np.array(weight.shape)
    cell = (points - grid["origin"]) / grid["voxel_size"]
    base = np.clip(np.floor(cell).astype(np.int64), 0, np.maximum(shape - 2, 0))
    fraction = np.clip(cell - base, 0.0, 1.0)
    total = np.zeros((points.shape[0], 3))
    mass = np.zeros(points.shape[0])
    for corner in range(8):
        offset = np.array([(corner >> 2) & 1, (corner >> 1) & 1, corner & 1])
        index = np.minimum(base + offset, shape - 1)
        share = np.prod(np.where(offset == 1, fraction, 1.0 - fraction), axis=1)
        i, j, k = index.T
        total += share[:, None] * color[i, j, k]
        mass += share * weight[i, j, k]
    rgb = np.where(mass[:, None] > 1e-6, total / np.maximum(mass, 1e-6)[:, None], 0.5)
    return np.clip(np.round(rgb * 255.0), 0, 255).astype(np.uint8)


def extract_surface(views: list[CanonicalView], *, triangles: int = DEFAULT_TRIANGLES, skeleton=None,
                    box: tuple | None = None, voxel_size: float | None = None, max_voxels: int = MAX_VOXELS,
                    device=None) -> trimesh.Trimesh:
    """A closed, decimated surface of the object the views show, floaters dropped, normals outwards.

    Steps: fuse the views into a TSDF with space carving (:func:`warpavatar.ops.integrate_tsdf`), over ``box`` or
    else over the visual hull's box (a coarse pass of :data:`COARSE_VOXELS` per axis over the region every camera
    frames); marching cubes on the fine grid padded with empty voxels (so the surface is closed, watertight);
    drop components that are cavities (wound inwards: the inner wall of a hollow), specks (enclosing less than
    :data:`SPECK_VOXELS` voxels) or floaters; decimate the rest to ``triangles`` (quadric edge collapse,
    fast-simplification); drop the folds decimation leaves (a triangle wound both ways) and give sheets that it
    pinched together their own vertices (every edge between two faces again); drop what decimation flattened.

    The floater rule: a component whose area is below :data:`FLOATER_AREA_FRACTION` of the largest kept
    component's, and none of whose vertices is within :data:`FLOATER_BONE_REACH` times the skeleton's height of
    one of its bones (segment head to tail), is dropped; without a ``skeleton`` every such small component is.

    Args:
        views: renders of the canonical avatar (:func:`warpavatar.mesh.views.render_canonical_views`), all of one
            size, with colour, alpha and expected depth.
        triangles: most triangles of the result (decimated to about this many when the fused surface has more).
        skeleton: the avatar's :class:`~warpavatar.data.Skeleton` (``heads``, ``tails``, ``up``) for the floater
            rule, or None.
        box: ``(low [3], high [3])`` [m] to fuse over (e.g. :func:`warpavatar.mesh.views.canonical_box`), or None
            for the visual hull's box.
        voxel_size: voxel size [m] of the fine grid; default :func:`default_voxel_size` (the renders' pixel
            footprint over :data:`VOXELS_PER_PIXEL`, at most ``max_voxels`` voxels).
        max_voxels: most voxels of the fine grid, for the default voxel size.
        device: where to run the fusion kernel (default CPU).

    Returns:
        a ``trimesh.Trimesh`` in the views' world frame [m], not processed (no vertices merged: sheets that
        touch keep their own): watertight (every edge between two faces), faces counter-clockwise seen from
        outside, vertex colours (RGBA uint8) from the fused renders (un-premultiplied by alpha), at most
        ``triangles`` faces; ``metadata["voxel_size"]`` the fine grid's voxel size [m].

    Raises:
        ValueError: no views, views of different sizes, ``triangles`` < 4, or nothing left to make a surface of.
    """
    if int(triangles) < 4:
        raise ValueError(f"extract_surface: triangles must be at least 4, got {triangles}")
    triangles = int(triangles)
    device = torch.device("cpu" if device is None else device)
    stacked = _stack_views(views, device)  # checks the views before any work
    if box is None:
        low, high = _hull_box(views, device, stacked)
    else:
        low, high = (np.asarray(corner, np.float64).reshape(3) for corner in box)
        if not np.all(high > low):
            raise ValueError(f"extract_surface: box must have high > low on every axis, got {low} and {high}")
    voxel_size = default_voxel_size(views, low, high, max_voxels=max_voxels) if voxel_size is None \
        else float(voxel_size)
    if not voxel_size > 0.0:
        raise ValueError(f"extract_surface: voxel_size must be positive, got {voxel_size}")
    grid = fuse_views(stacked, low, high, voxel_size, device=device)
    vertices, faces = _marching_cubes(grid, offset=depth_offset(grid))
    if faces.shape[0] == 0:
        raise ValueError("extract_surface: the views show nothing to make a surface of")
    vertices, faces = _compacted(vertices, faces[_kept_components(vertices, faces, skeleton, voxel_size)])
    if faces.shape[0] == 0:
        raise ValueError("extract_surface: no component of the fused surface is left (all floaters)")
    vertices, faces = _decimated(vertices, faces, triangles)
    faces = faces[(faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 2] != faces[:, 0])]
    vertices, faces = _manifold(*_compacted(vertices, _without_folds(faces)))
    # decimation may flatten a small component into a sliver: the rule again drops what no longer encloses much
    vertices, faces = _compacted(vertices, faces[_kept_components(vertices, faces, skeleton, voxel_size)])
    if faces.shape[0] == 0:
        raise ValueError("extract_surface: nothing of the fused surface is left after decimation")
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    colors = _sample_colors(grid, vertices)
    mesh.visual = trimesh.visual.ColorVisuals(
        mesh, vertex_colors=np.concatenate([colors, np.full((colors.shape[0], 1), 255, np.uint8)], axis=1))
    mesh.metadata["voxel_size"] = float(voxel_size)
    return mesh
