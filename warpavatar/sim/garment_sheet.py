"""A garment's surface as a triangle sheet, built template-free from its Gaussians (the cloth a sheet simulation
steps and triangle-bound Gaussians ride on).

The sheet is a surface of revolution about the attachment joint's axis, bent to the data: a grid of ``rings`` x
``segments`` vertices parametrised by a height ``t`` down the garment and an angle ``theta`` about the axis, whose
distance from the axis comes from the garment points' outer envelope. Ring 0 is the waistband (pinned to the body
by the caller), the last ring the hem (an open boundary).

Coordinates. With ``o`` the axis origin, ``a`` the unit axis (pointing down the garment), ``e_x, e_y`` a basis of
the plane across it, a point ``p`` has height ``h = (p - o) . a``, radius ``r`` (its distance from the axis) and
angle ``theta = atan2((p - o) . e_y, (p - o) . e_x)``. A skirt that flares is a cone, not a cylinder, so the sheet's
rows follow the garment's *meridian* rather than the axis: the cone angle ``alpha`` is the direction of the
garment's (h, r) profile (principal direction of the points' (h, r), fitted again on the points near the first
envelope, so points inside the garment do not tilt it), and each point gets the meridian coordinates::

    t = h cos(alpha) + r sin(alpha)        (along the cone, from the waistband to the hem)
    n = -h sin(alpha) + r cos(alpha)       (across it, outwards)

``alpha = 0`` is a tube (``t = h``, ``n = r``); a skirt wider than it is long has ``alpha`` near 90 degrees, where
the rows are concentric rings of a flat annulus (``t`` is then the distance from the axis) and equal steps in ``t``
still give well-shaped triangles, which equal steps in height would not. ``alpha`` is kept in [-80, 89] degrees.

The envelope ``n = N(t, theta)``. The points are binned in (t, theta) on a grid coarser than the mesh, sized so that
a bin holds about ``bin_points`` points; each bin's value is the ``envelope_quantile`` of ``n`` of its points (the
outer surface: points inside the garment, its far side's back, the body under it lie below it), then refined twice
on the residuals ``n - N(t, theta)`` interpolated at each point (a bin's quantile of raw ``n`` would sit at the top
of the bin's slope: half a bin too far out on a flared skirt). Bins with fewer than ``min_bin_points`` points are
empty: filled along the angle from their ring's other bins (periodically on a closed sheet), rows with none at all
from the neighbouring rows along ``t``; the grid is then smoothed by ``smoothing`` passes of a [1, 2, 1] / 4 filter
along both directions. The mesh's vertices sample it bilinearly. The height range runs from the ``1 -
extent_quantile`` quantile of ``t`` (the waistband) to its ``extent_quantile`` quantile (the hem), so a few stray
points neither lift the waistband nor lengthen the hem.

Partial garments. A coat's tails cover the back only: the angles hold a gap. The angles are histogrammed in 5-degree
bins; bins holding under a tenth of the mean count are empty, and the largest circular run of empty bins is the
gap. When the occupied span (360 degrees minus that gap) is below ``open_span_degrees``, the sheet is *open*: it
spans only the occupied angles (from the ``1 - extent_quantile`` to the ``extent_quantile`` quantile of the
points' angles, unwrapped across the gap), ``segments + 1`` vertices a ring, with two free side edges. Otherwise it
is a closed tube of ``segments`` vertices a ring (a skirt that leaves a narrow slit still gets a full ring: a slit
narrower than ``360 - open_span_degrees`` is taken for missing points, not for an opening).

Mesh. Quads split into two triangles with alternating diagonals (no preferred shear direction); built with trimesh
(``process=False``: no vertex is merged), degenerate triangles removed and unused vertices dropped (ids
remapped), triangles wound so that their normals point outwards (away from the axis along ``n``). UVs are (``u``:
the angle's fraction of the sheet's span, ``v``: the ring's fraction from the waistband, 0, to the hem, 1); a closed
sheet's seam at ``u = 0`` shares its vertices (the cloth has no cut there), so ``u`` wraps from
``(segments - 1) / segments`` to 0 across its last column of triangles. :meth:`GarmentSheet.write` writes ``.ply``
or ``.obj`` atomically for inspection.

The training silhouettes are not used here: the sheet is fitted to the canonical garment Gaussians alone (a refinement
against the masks needs the sheet skinned to each training frame, which belongs to the garment's fit).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from warpavatar.io.output_files import write_bytes_atomic, write_text_atomic

__all__ = ["GarmentSheet", "build_garment_sheet", "ANGLE_HISTOGRAM_BINS", "CONE_ANGLE_RANGE_DEGREES"]

ANGLE_HISTOGRAM_BINS = 72
"""Angle bins (5 degrees each) of the occupancy histogram that finds a partial garment's gap."""

CONE_ANGLE_RANGE_DEGREES = (-80.0, 89.0)
"""The cone angle is clamped to this range [degrees] (negative: a garment narrowing downwards)."""

_EMPTY_BIN_SHARE = 0.1  # an angle bin holding less than this share of the mean count is empty


@dataclass(frozen=True)
class GarmentSheet:
    """A garment's rest surface as a triangle sheet (module docstring).

    Attributes:
        vertices: float64 ``[V, 3]`` rest positions [world units] (canonical space).
        faces: int64 ``[F, 3]`` vertex ids of each triangle, wound so normals point outwards.
        uv: float64 ``[V, 2]`` (angle fraction, height fraction) in [0, 1]; v = 0 at the waistband.
        ring_ids: int64 ``[V]`` each vertex's ring, 0 (waistband) to ``rings - 1`` (hem).
        column_ids: int64 ``[V]`` each vertex's column around the axis.
        pinned: int64 ``[P]`` the waistband's vertex ids (ring 0), in column order.
        is_open: True when the sheet spans only the occupied angles (a partial garment).
        angle_range: (start, end) [rad] of the sheet's span about the axis, end > start (end - start = 2 pi for a
            closed sheet).
        cone_angle: ``alpha`` [rad] of the meridian coordinates.
        axis_origin, axis_direction, axis_basis: the frame: origin [3], unit axis [3], and ``e_x, e_y`` ``[2, 3]``.
        mesh: the trimesh.Trimesh (vertices, faces, UVs) for inspection and export.
    """

    vertices: np.ndarray
    faces: np.ndarray
    uv: np.ndarray
    ring_ids: np.ndarray
    column_ids: np.ndarray
    pinned: np.ndarray
    is_open: bool
    angle_range: tuple[float, float]
    cone_angle: float
    axis_origin: np.ndarray
    axis_direction: np.ndarray
    axis_basis: np.ndarray
    mesh: trimesh.Trimesh

    @property
    def ring_count(self) -> int:
        return int(self.ring_ids.max()) + 1 if self.ring_ids.size else 0

    @property
    def hem(self) -> np.ndarray:
        """Vertex ids of the last ring (the hem), in column order."""
        ids = np.nonzero(self.ring_ids == self.ring_count - 1)[0]
        return ids[np.argsort(self.column_ids[ids], kind="stable")]

    def boundary_edges(self) -> np.ndarray:
        """int64 ``[B, 2]`` the edges of one triangle only (the waistband, the hem, an open sheet's sides)."""
        edges = self.mesh.edges_sorted
        return edges[trimesh.grouping.group_rows(edges, require_count=1)]

    def write(self, path: str | os.PathLike) -> Path:
        """Write the sheet for inspection, atomically: ``.ply`` (binary, with the UVs as ``s, t``) or ``.obj``
        (text, UVs as ``vt``, normals, no material).

        Raises:
            ValueError: another file suffix.
        """
        path = Path(path)
        suffix = path.suffix.lower()
        if suffix == ".ply":
            return write_bytes_atomic(path, self.mesh.export(file_type="ply"))
        if suffix == ".obj":
            text = trimesh.exchange.obj.export_obj(self.mesh, include_normals=True, include_texture=True,
                                                   write_texture=False)
            text = "\n".join(line for line in text.splitlines() if not line.startswith(("mtllib", "usemtl")))
            return write_text_atomic(path, text + "\n")
        raise ValueError(f"{path}: a garment sheet is written as .ply or .obj, got suffix {path.suffix!r}")


# ------------------------------------------------------------------------------------------------ the frame
def _unit(vector, name: str) -> np.ndarray:
    vector = np.asarray(vector, dtype=np.float64).reshape(-1)
    if vector.shape != (3,) or not np.isfinite(vector).all():
        raise ValueError(f"{name} must be 3 finite numbers, got {vector.tolist()}")
    length = np.linalg.norm(vector)
    if length < 1e-12:
        raise ValueError(f"{name} must not be zero")
    return vector / length


def _axis_basis(axis: np.ndarray, reference) -> np.ndarray:
    """``e_x, e_y`` [2, 3]: ``e_x`` the reference direction made perpendicular to the axis (by default the world
    axis least aligned with it), ``e_y = axis x e_x``."""
    if reference is None:
        reference = np.eye(3)[int(np.argmin(np.abs(axis)))]
    reference = _unit(reference, "reference_direction")
    across = reference - axis * (reference @ axis)
    if np.linalg.norm(across) < 1e-6:
        raise ValueError("reference_direction must not be parallel to axis_direction")
    across /= np.linalg.norm(across)
    return np.stack([across, np.cross(axis, across)])


def _cone_angle(h: np.ndarray, r: np.ndarray) -> float:
    """Principal direction of the (h, r) profile as an angle from the axis [rad], oriented away from the origin."""
    profile = np.stack([h, r], axis=1)
    centred = profile - profile.mean(axis=0)
    _, vectors = np.linalg.eigh(centred.T @ centred)
    direction = vectors[:, -1]
    if np.dot(centred @ direction, np.linalg.norm(profile, axis=1) - np.linalg.norm(profile, axis=1).mean()) < 0:
        direction = -direction
    low, high = np.radians(CONE_ANGLE_RANGE_DEGREES)
    return float(np.clip(math.atan2(direction[1], direction[0]), low, high))


# ------------------------------------------------------------------------------------------ angular coverage
def _angular_span(theta: np.ndarray, *, open_span_degrees: float, extent_quantile: float
                  ) -> tuple[bool, float, float]:
    """(is_open, start, end) [rad] of the sheet's span about the axis (module docstring)."""
    bins = ANGLE_HISTOGRAM_BINS
    counts = np.bincount(np.floor((theta + math.pi) / (2 * math.pi) * bins).astype(np.int64) % bins,
                         minlength=bins)
    empty = counts < _EMPTY_BIN_SHARE * counts.mean()
    if not empty.any():
        return False, -math.pi, math.pi
    # the largest circular run of empty bins
    best_length, best_end = 0, 0
    run = 0
    for index in range(2 * bins):
        run = run + 1 if empty[index % bins] else 0
        if run > best_length:
            best_length, best_end = min(run, bins), index % bins
    gap_degrees = best_length * 360.0 / bins
    if 360.0 - gap_degrees >= open_span_degrees:
        return False, -math.pi, math.pi
    gap_centre = -math.pi + (best_end + 1 - best_length / 2.0) * 2 * math.pi / bins
    # angles unwrapped to start just after the gap's centre
    unwrapped = np.mod(theta - gap_centre, 2 * math.pi) + gap_centre
    start = float(np.quantile(unwrapped, 1.0 - extent_quantile))
    end = float(np.quantile(unwrapped, extent_quantile))
    return True, start, end


# ------------------------------------------------------------------------------------------- the envelope fit
class _Grid:
    """A (t, theta) grid of envelope values: rows at ``t_nodes``, columns at ``theta_nodes`` (periodic when
    closed), with bilinear interpolation."""

    def __init__(self, t_nodes: np.ndarray, theta_nodes: np.ndarray, *, closed: bool):
        self.t_nodes, self.theta_nodes, self.closed = t_nodes, theta_nodes, closed

    def _axis(self, nodes: np.ndarray, values: np.ndarray, periodic: bool):
        """Lower node, upper node and weight of the upper one for each value."""
        count = nodes.shape[0]
        if count == 1:
            zeros = np.zeros(values.shape, dtype=np.int64)
            return zeros, zeros, np.zeros(values.shape)
        step = nodes[1] - nodes[0]
        position = (values - nodes[0]) / step
        if periodic:
            low = np.floor(position).astype(np.int64)
            weight = position - low
            return low % count, (low + 1) % count, weight
        position = np.clip(position, 0.0, count - 1)
        low = np.minimum(np.floor(position).astype(np.int64), count - 2)
        return low, low + 1, position - low

    def cells(self, t: np.ndarray, theta: np.ndarray):
        """Nearest node (row, column) of each point: its bin."""
        rows = np.clip(np.rint((t - self.t_nodes[0]) / max(self._t_step(), 1e-30)), 0, len(self.t_nodes) - 1)
        position = (theta - self.theta_nodes[0]) / self._theta_step()
        if self.closed:
            columns = np.rint(position).astype(np.int64) % len(self.theta_nodes)
        else:
            columns = np.clip(np.rint(position), 0, len(self.theta_nodes) - 1).astype(np.int64)
        return rows.astype(np.int64), columns

    def _t_step(self) -> float:
        return float(self.t_nodes[1] - self.t_nodes[0]) if len(self.t_nodes) > 1 else 1.0

    def _theta_step(self) -> float:
        return float(self.theta_nodes[1] - self.theta_nodes[0]) if len(self.theta_nodes) > 1 else 1.0

    def sample(self, values: np.ndarray, t: np.ndarray, theta: np.ndarray) -> np.ndarray:
        r0, r1, wr = self._axis(self.t_nodes, t, False)
        c0, c1, wc = self._axis(self.theta_nodes, theta, self.closed)
        top = values[r0, c0] * (1 - wc) + values[r0, c1] * wc
        bottom = values[r1, c0] * (1 - wc) + values[r1, c1] * wc
        return top * (1 - wr) + bottom * wr


def _fill_line(line: np.ndarray, periodic: bool) -> np.ndarray:
    """NaN entries of a 1D array filled by linear interpolation of the others (periodic, or nearest at the ends)."""
    known = np.isfinite(line)
    if known.all() or not known.any():
        return line
    index = np.arange(line.shape[0], dtype=np.float64)
    if periodic:
        return np.interp(index, index[known], line[known], period=line.shape[0])
    return np.interp(index, index[known], line[known])


def _fill_and_smooth(grid: np.ndarray, *, closed: bool, passes: int) -> np.ndarray:
    grid = grid.copy()
    for row in range(grid.shape[0]):
        grid[row] = _fill_line(grid[row], closed)
    for column in range(grid.shape[1]):
        grid[:, column] = _fill_line(grid[:, column], False)
    for _ in range(passes):
        if grid.shape[1] > 2:
            left = np.roll(grid, 1, axis=1) if closed else np.concatenate([grid[:, :1], grid[:, :-1]], axis=1)
            right = np.roll(grid, -1, axis=1) if closed else np.concatenate([grid[:, 1:], grid[:, -1:]], axis=1)
            grid = 0.25 * left + 0.5 * grid + 0.25 * right
        if grid.shape[0] > 2:
            up = np.concatenate([grid[:1], grid[:-1]], axis=0)
            down = np.concatenate([grid[1:], grid[-1:]], axis=0)
            grid = 0.25 * up + 0.5 * grid + 0.25 * down
    return grid


def _bin_quantiles(values: np.ndarray, rows: np.ndarray, columns: np.ndarray, shape: tuple[int, int], *,
                   quantile: float, min_points: int) -> np.ndarray:
    """The ``quantile`` of ``values`` per (row, column) bin, NaN for bins of fewer than ``min_points``."""
    flat = rows * shape[1] + columns
    order = np.argsort(flat, kind="stable")
    flat_sorted, values_sorted = flat[order], values[order]
    starts = np.searchsorted(flat_sorted, np.arange(shape[0] * shape[1]))
    ends = np.searchsorted(flat_sorted, np.arange(shape[0] * shape[1]), side="right")
    out = np.full(shape[0] * shape[1], np.nan)
    for cell, (start, end) in enumerate(zip(starts, ends)):
        if end - start >= min_points:
            out[cell] = np.quantile(values_sorted[start:end], quantile)
    return out.reshape(shape)


def _fit_envelope(t, theta, n, grid: _Grid, *, quantile: float, min_points: int, passes: int,
                  refinements: int = 2) -> np.ndarray:
    shape = (len(grid.t_nodes), len(grid.theta_nodes))
    rows, columns = grid.cells(t, theta)
    values = _fill_and_smooth(_bin_quantiles(n, rows, columns, shape, quantile=quantile, min_points=min_points),
                              closed=grid.closed, passes=passes)
    if not np.isfinite(values).all():
        raise ValueError("the garment points fill no bin of the envelope fit: too few points")
    for _ in range(refinements):
        residual = n - grid.sample(values, t, theta)
        correction = _bin_quantiles(residual, rows, columns, shape, quantile=quantile, min_points=min_points)
        values = values + _fill_and_smooth(correction, closed=grid.closed, passes=passes)
    return values


def _nodes(low: float, high: float, count: int, *, closed: bool) -> np.ndarray:
    if closed:
        return low + (high - low) * np.arange(count) / count
    return np.linspace(low, high, count) if count > 1 else np.array([0.5 * (low + high)])


# ------------------------------------------------------------------------------------------------ the sheet
def build_garment_sheet(garment_points, *, axis_origin, axis_direction, rings: int = 16, segments: int = 32,
                        envelope_quantile: float = 0.9, extent_quantile: float = 0.99,
                        open_span_degrees: float = 300.0, bin_points: int = 30, min_bin_points: int = 4,
                        smoothing: int = 1, min_radius: float = 1e-3, reference_direction=None) -> GarmentSheet:
    """Build a garment's rest sheet from its canonical points (module docstring).

    Args:
        garment_points: float ``[N, 3]`` the garment Gaussians' canonical centres [world units] (numpy or torch).
        axis_origin: ``[3]`` where the garment hangs from (the attachment joint's head) [world units].
        axis_direction: ``[3]`` down the garment (e.g. minus the skeleton's up); normalized here.
        rings: rings of vertices from the waistband (ring 0, pinned) to the hem (>= 2).
        segments: vertices a ring around a closed sheet (>= 3); an open sheet has ``segments + 1``.
        envelope_quantile: quantile of the points' distance from the axis that is the garment's outer surface.
        extent_quantile: quantile of the points' height (and, for an open sheet, angle) where the hem (its sides)
            lie; ``1 - extent_quantile`` places the waistband (the first side).
        open_span_degrees: an occupied angular span below this gives an open sheet [degrees].
        bin_points: points per bin of the envelope fit, on average (sizes the fit's grid).
        min_bin_points: a bin with fewer points is filled from its neighbours.
        smoothing: passes of the [1, 2, 1] / 4 filter over the fitted envelope.
        min_radius: the sheet keeps at least this distance from the axis [world units].
        reference_direction: ``[3]`` the direction of angle 0 (projected across the axis); default the world
            axis least aligned with the axis.

    Returns:
        The :class:`GarmentSheet`.

    Raises:
        ValueError: too few or non-finite points, a zero axis, options out of range.
    """
    points = np.asarray(garment_points.detach().cpu() if hasattr(garment_points, "detach") else garment_points,
                        dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"garment_points must have shape [N, 3], got {list(points.shape)}")
    if not np.isfinite(points).all():
        raise ValueError("garment_points must be finite")
    for name, value, low in (("rings", rings, 2), ("segments", segments, 3), ("bin_points", bin_points, 1),
                             ("min_bin_points", min_bin_points, 1), ("smoothing", smoothing, 0)):
        if isinstance(value, bool) or not isinstance(value, int) or value < low:
            raise ValueError(f"{name} must be an int >= {low}, got {value!r}")
    for name, value in (("envelope_quantile", envelope_quantile), ("extent_quantile", extent_quantile)):
        if not 0.5 <= value <= 1.0:
            raise ValueError(f"{name} must be in [0.5, 1], got {value}")
    if not 0.0 < open_span_degrees <= 360.0:
        raise ValueError(f"open_span_degrees must be in (0, 360], got {open_span_degrees}")
    if not min_radius > 0:
        raise ValueError(f"min_radius must be positive, got {min_radius}")
    if points.shape[0] < 4 * min_bin_points:
        raise ValueError(f"a garment sheet needs at least {4 * min_bin_points} garment points, got {points.shape[0]}")
    origin = np.asarray(axis_origin, dtype=np.float64).reshape(-1)
    if origin.shape != (3,) or not np.isfinite(origin).all():
        raise ValueError(f"axis_origin must be 3 finite numbers, got {origin.tolist()}")
    axis = _unit(axis_direction, "axis_direction")
    basis = _axis_basis(axis, reference_direction)

    offset = points - origin
    h = offset @ axis
    across = offset @ basis.T  # [N, 2]
    r = np.linalg.norm(across, axis=1)
    theta = np.arctan2(across[:, 1], across[:, 0])
    is_open, start, end = _angular_span(theta, open_span_degrees=open_span_degrees, extent_quantile=extent_quantile)
    if is_open:  # the points' angles unwrapped into the sheet's span
        middle = 0.5 * (start + end)
        theta = np.mod(theta - middle + math.pi, 2 * math.pi) + middle - math.pi
    closed = not is_open

    # the fit's grid: about bin_points points a bin, the mesh's aspect, never finer than the mesh
    total_bins = max(4, points.shape[0] // bin_points)
    fit_rings = int(np.clip(round(math.sqrt(total_bins * rings / segments)), 2, rings))
    fit_columns = int(np.clip(total_bins // fit_rings, 3 if closed else 2, segments))

    def fit(alpha: float, near: np.ndarray):
        t = h * math.cos(alpha) + r * math.sin(alpha)
        n = -h * math.sin(alpha) + r * math.cos(alpha)
        t_top = float(np.quantile(t[near], 1.0 - extent_quantile))
        t_hem = float(np.quantile(t[near], extent_quantile))
        if not t_hem > t_top:
            raise ValueError("the garment points have no extent along the axis")
        grid = _Grid(_nodes(t_top, t_hem, fit_rings, closed=False), _nodes(start, end, fit_columns, closed=closed),
                     closed=closed)
        envelope = _fit_envelope(t, theta, n, grid, quantile=envelope_quantile, min_points=min_bin_points,
                                 passes=smoothing)
        return t, n, t_top, t_hem, grid, envelope

    # the cone angle and the height range again from the points near the envelope (points inside the garment
    # tilt the profile less than its surface and, on a flared garment, reach above its waistband along t)
    alpha, near = _cone_angle(h, r), np.ones(points.shape[0], dtype=bool)
    for _ in range(2):
        t, n, t_top, t_hem, grid, envelope = fit(alpha, near)
        residual = n - grid.sample(envelope, t, theta)
        band = np.quantile(np.abs(residual), 0.5) * 3.0 + 1e-9
        if (residual > -band).sum() < 4 * min_bin_points:
            break
        near = residual > -band
        alpha = _cone_angle(h[near], r[near])
    t, n, t_top, t_hem, grid, envelope = fit(alpha, near)

    # the mesh: rings x columns vertices sampling the envelope
    columns = segments if closed else segments + 1
    ring_t = np.linspace(t_top, t_hem, rings)
    column_theta = _nodes(start, end, segments, closed=True) if closed else np.linspace(start, end, columns)
    tt, aa = np.meshgrid(ring_t, column_theta, indexing="ij")  # [rings, columns]
    nn = grid.sample(envelope, tt.reshape(-1), aa.reshape(-1)).reshape(tt.shape)
    height = tt * math.cos(alpha) - nn * math.sin(alpha)
    radius = np.maximum(tt * math.sin(alpha) + nn * math.cos(alpha), min_radius)
    directions = np.cos(aa)[..., None] * basis[0] + np.sin(aa)[..., None] * basis[1]
    vertices = (origin + height[..., None] * axis + radius[..., None] * directions).reshape(-1, 3)
    ring_ids = np.repeat(np.arange(rings), columns)
    column_ids = np.tile(np.arange(columns), rings)
    uv = np.stack([column_ids / (segments if closed else columns - 1), ring_ids / (rings - 1)], axis=1)

    faces = []
    for i in range(rings - 1):
        for j in range(segments):
            j1 = (j + 1) % columns
            a, b, c, d = i * columns + j, i * columns + j1, (i + 1) * columns + j1, (i + 1) * columns + j
            faces += [[a, b, c], [a, c, d]] if (i + j) % 2 == 0 else [[a, b, d], [b, c, d]]
    faces = np.asarray(faces, dtype=np.int64)

    mesh = trimesh.Trimesh(vertices, faces, process=False)
    mesh.update_faces(mesh.nondegenerate_faces())
    used = np.zeros(len(vertices), dtype=bool)
    used[mesh.faces.reshape(-1)] = True
    remap = np.cumsum(used) - 1
    vertices, faces = vertices[used], remap[mesh.faces]
    uv, ring_ids, column_ids = uv[used], ring_ids[used], column_ids[used]
    # outward: along n, the direction (-sin alpha) axis + (cos alpha) radial, at each triangle's centroid
    centroid = vertices[faces].mean(axis=1)
    radial = (centroid - origin) - np.outer((centroid - origin) @ axis, axis)
    radial /= np.maximum(np.linalg.norm(radial, axis=1, keepdims=True), 1e-12)
    outward = -math.sin(alpha) * axis + math.cos(alpha) * radial
    normals = np.cross(vertices[faces[:, 1]] - vertices[faces[:, 0]], vertices[faces[:, 2]] - vertices[faces[:, 0]])
    if np.sum(normals * outward) < 0:
        faces = faces[:, ::-1].copy()
    mesh = trimesh.Trimesh(vertices, faces, process=False, visual=trimesh.visual.TextureVisuals(uv=uv))
    pinned = np.nonzero(ring_ids == 0)[0]
    pinned = pinned[np.argsort(column_ids[pinned], kind="stable")]
    return GarmentSheet(vertices=vertices, faces=faces, uv=uv, ring_ids=ring_ids, column_ids=column_ids,
                        pinned=pinned, is_open=is_open, angle_range=(float(start), float(end)),
                        cone_angle=float(alpha), axis_origin=origin, axis_direction=axis, axis_basis=basis, mesh=mesh)
