"""Exact k-nearest-neighbour graph of a point cloud on a Warp hash grid (the Gaussian graph of SMAD).

The public function is :func:`knn_graph`; the kernels are in :mod:`warpavatar.kernels.knn`, a brute-force
torch reference with the same signature in :mod:`warpavatar._torch_impl.knn`.

How the search is organised (one call, a handful of launches and host synchronizations; the graph is built
once per avatar, so these syncs are not in a training loop):

1. Statistics: bounding box, a centred copy of the points (the grid is built on it) and the median exact
   k-th neighbour distance of a few evenly spaced sample points (brute force over all points). The first
   host synchronization reads them.
2. Cell width: the median k-th neighbour distance (so a query's k neighbours typically lie in its own and
   the next ring of cells, whatever the intrinsic dimension of the data: volume, surface or curve), capped
   by ``max_radius`` and floored where float32 could no longer tell cells apart.
3. Level 0: a :class:`warp.HashGrid` at that width; one thread per point in the grid's sorted order scans
   rings of cells until its k-th distance is certified (every point outside the scanned block is at least
   that far), for at most a few rings. Queries left unfinished (sparse regions, outliers) are listed.
4. Levels 1, 2, ...: the unfinished queries are searched again on grids four times coarser, until none is
   left; the last level's block covers every point, so the result is always exact (the worst case degrades
   to brute force for those few queries only).
"""

from __future__ import annotations

import math
import numbers

import numpy as np
import torch
import warp as wp

from warpavatar._src.warp_utils import check_tensor, to_warp, torch_stream_scope
from warpavatar.kernels.knn import (
    MAX_K,
    cell_width_inverse,
    launch_knn_query,
    launch_knn_sample,
)

__all__ = ["knn_graph"]

_RING_LIMIT = 3
"""Rings of cells a query scans on one level before it is handed to the next, coarser level."""

_LEVEL_GROWTH = 4.0
"""Cell width ratio between consecutive levels (> _RING_LIMIT would leave gaps in certified radii)."""

_CELLS_PER_POINT = 2
"""Hash-grid cells allocated per point (at least _MIN_CELLS); beyond that, cells alias modulo the grid."""

_MIN_CELLS = 4096

_SAMPLES = {"cuda": 256, "cpu": 64}
"""Sample points of the cell-width estimate, per device type."""

_SAMPLE_CHUNK_CUDA = 4096
"""Smallest number of points per thread of the brute-force sample kernel on CUDA (on CPU one chunk holds
all points)."""

_CELL_SCALE = 1.0
"""Cell width over the median k-th neighbour distance."""

_COORDINATE_EPS = 2.0**-19
"""Relative bound (of the largest centred coordinate) on float32 rounding of cell membership."""

_CELL_FLOOR = 2.0**-16
"""Smallest cell width, relative to the largest centred coordinate."""


def knn_graph(
    points: torch.Tensor, k: int, *, max_radius: float | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Exact k nearest other points of every point (k-NN graph), on a Warp hash grid.

    A point is never its own neighbour; duplicates of a point are other points, at distance 0. Neighbours of
    each point are sorted nearest first (points at equal distance in any order). The search is exact for any
    distribution (uniform, surface-like, clustered, with far outliers): see the module docstring.

    Args:
        points: positions [world units], float tensor of shape ``[M, 3]`` on CPU or CUDA; computed in
            float32 (other float dtypes are converted). Every coordinate must be finite.
        k: neighbours per point, ``1 <= k <= 64`` (one kernel is compiled per distinct ``k``).
        max_radius: when given, only neighbours at distance ``<= max_radius`` are kept (compared as squared
            float32 distances); must be ``>= 0``. ``None`` (default) or ``inf``: no limit.

    Returns:
        ``(index, distance)``:
            * ``index``: int64 ``[M, k]``; ``index[i, n]`` is the n-th nearest other point of point ``i``;
              ``-1`` pads a row when fewer than ``k`` other points exist (``M - 1 < k``) or lie within
              ``max_radius``;
            * ``distance``: float32 ``[M, k]``, Euclidean distance (not squared) [world units] to
              ``index[i, n]``, ascending along a row; ``inf`` where ``index`` is ``-1``.
        Both on the device of ``points``. ``M == 0`` gives empty ``[0, k]`` tensors.

    Gradients: none. The graph is a constant of training; ``distance`` is returned detached (recompute
    ``(points[i] - points[index]).norm(dim=-1)`` in torch if a differentiable length is needed).

    Raises:
        TypeError: ``points`` is not a floating-point tensor, ``k`` not an integer, ``max_radius`` not a number.
        ValueError: bad shape, ``k`` out of range, negative or NaN ``max_radius``, non-finite coordinates.
    """
    check_tensor("points", points, (None, 3))
    if isinstance(k, bool) or not isinstance(k, numbers.Integral):
        raise TypeError(f"k must be an int, got {type(k).__name__}")
    k = int(k)
    if not 1 <= k <= MAX_K:
        raise ValueError(f"k must be in [1, {MAX_K}], got {k}")
    if max_radius is not None:
        if isinstance(max_radius, bool) or not isinstance(max_radius, numbers.Real):
            raise TypeError(f"max_radius must be a number or None, got {type(max_radius).__name__}")
        max_radius = float(max_radius)
        if math.isnan(max_radius) or max_radius < 0.0:
            raise ValueError(f"max_radius must be >= 0, got {max_radius}")

    device = points.device
    point_count = points.shape[0]
    if point_count <= 1:
        if point_count == 1 and not bool(torch.isfinite(points).all()):
            raise ValueError("points must be finite")
        return (
            torch.full((point_count, k), -1, dtype=torch.int64, device=device),
            torch.full((point_count, k), math.inf, dtype=torch.float32, device=device),
        )

    with torch.no_grad():
        positions = points.detach().to(torch.float32).contiguous()
        with torch_stream_scope(device):
            return _knn_graph(positions, k, max_radius)


def _knn_graph(positions: torch.Tensor, k: int, max_radius: float | None) -> tuple[torch.Tensor, torch.Tensor]:
    device = positions.device
    point_count = positions.shape[0]
    points_wp = to_warp(positions, wp.vec3)

    # 1. Bounding box, centred copy, median k-th neighbour distance of sample points: one host sync.
    lower, upper = torch.aminmax(positions, dim=0)
    centred = positions - (lower + upper) * 0.5
    centred_lower, centred_upper = torch.aminmax(centred, dim=0)
    effective_k = min(k, point_count - 1)
    median_kth_sq = _median_kth_distance_sq(points_wp, positions, k, effective_k)
    stats = torch.cat([centred_lower, centred_upper, median_kth_sq.view(1)]).cpu().numpy()
    centred_lower = stats[0:3].astype(np.float32)
    centred_upper = stats[3:6].astype(np.float32)
    if not (np.isfinite(centred_lower).all() and np.isfinite(centred_upper).all()):
        raise ValueError("points must be finite (found NaN or inf coordinates)")

    # 2. Cell width.
    largest = float(max(np.abs(centred_lower).max(), np.abs(centred_upper).max()))
    extent = float((centred_upper - centred_lower).max())
    slack = _COORDINATE_EPS * largest
    kth = math.sqrt(float(stats[6])) if np.isfinite(stats[6]) else 0.0
    if kth <= 0.0:  # e.g. most samples have k duplicates: fall back to the mean spacing
        kth = extent / point_count ** (1.0 / 3.0)
    cell_width = _CELL_SCALE * kth
    if max_radius is not None and max_radius > 0.0:
        cell_width = min(cell_width, max_radius)
    cell_width = max(cell_width, _CELL_FLOOR * largest)
    if not cell_width > 0.0:
        cell_width = 1.0  # all points coincide
    max_distance_sq = math.inf
    if max_radius is not None and math.isfinite(max_radius):
        radius_sq = np.float32(max_radius) * np.float32(max_radius)
        # Accept d^2 <= r^2: the threshold is the next float32 up (a normal number, so no flush-to-zero).
        max_distance_sq = float(max(np.nextafter(radius_sq, np.float32(np.inf)), np.finfo(np.float32).tiny))

    index = torch.empty((point_count, k), dtype=torch.int64, device=device)
    distance = torch.empty((point_count, k), dtype=torch.float32, device=device)
    index_wp = to_warp(index)
    distance_wp = to_warp(distance)
    centred_wp = to_warp(centred, wp.vec3)
    # Ping-pong lists of unfinished query ids (the second one is allocated when a second level runs).
    unfinished = [torch.empty(point_count, dtype=torch.int32, device=device)]
    unfinished_wp = [to_warp(unfinished[0])]
    cell_budget = max(_MIN_CELLS, _CELLS_PER_POINT * point_count)

    # 3-4. Levels of ring search, each on a grid four times coarser than the last, over unfinished queries.
    query_ids_wp = None
    query_count = point_count
    level = 0
    while True:
        cell_width = float(np.float32(cell_width))
        inverse = np.float32(cell_width_inverse(cell_width))
        lo_cell = tuple(int(v) for v in np.floor(centred_lower * inverse))
        hi_cell = tuple(int(v) for v in np.floor(centred_upper * inverse))
        extent_cells = [hi - lo + 1 for lo, hi in zip(lo_cell, hi_cell)]
        dims = _grid_dims(extent_cells, cell_budget)
        aliased = [d for d, n in zip(dims, extent_cells) if d < n]
        alias_dim = min(aliased) if aliased else 2**30

        grid = wp.HashGrid(*dims, device=centred_wp.device)
        grid.build(centred_wp, cell_width)
        unfinished_count = torch.zeros(1, dtype=torch.int32, device=device)
        if level == 1 and len(unfinished) == 1:
            unfinished.append(torch.empty(point_count, dtype=torch.int32, device=device))
            unfinished_wp.append(to_warp(unfinished[1]))
        out_ids_wp = unfinished_wp[level % 2]
        launch_knn_query(
            grid,
            points_wp,
            centred_wp,
            query_ids_wp,
            query_count,
            k=k,
            cell_width=cell_width,
            slack=slack,
            lo_cell=lo_cell,
            hi_cell=hi_cell,
            ring_limit=_RING_LIMIT,
            alias_dim=alias_dim,
            max_distance_sq=max_distance_sq,
            out_index=index_wp,
            out_distance=distance_wp,
            unfinished_ids=out_ids_wp,
            unfinished_count=to_warp(unfinished_count),
        )
        # Reading the count also guarantees the grid is no longer in use when it is released.
        query_count = int(unfinished_count.item())
        del grid
        if query_count == 0:
            break
        if max(extent_cells) - 1 <= _RING_LIMIT:
            raise RuntimeError("knn_graph: a query was left unfinished although its search covered all points")
        query_ids_wp = out_ids_wp
        cell_width *= _LEVEL_GROWTH
        level += 1
    return index, distance


def _median_kth_distance_sq(
    points_wp: wp.array, positions: torch.Tensor, k: int, effective_k: int
) -> torch.Tensor:
    """Median over evenly spaced sample points of their exact squared ``effective_k``-th neighbour distance."""
    device = positions.device
    point_count = positions.shape[0]
    sample_count = min(point_count, _SAMPLES["cuda" if device.type == "cuda" else "cpu"])
    sample_ids = (torch.arange(sample_count, device=device) * point_count // sample_count).to(torch.int32)
    if device.type == "cuda":  # at most 256 chunks, so the partial lists stay small
        chunk_size = max(_SAMPLE_CHUNK_CUDA, -(-point_count // 256))
    else:
        chunk_size = point_count
    chunk_count = (point_count + chunk_size - 1) // chunk_size
    partial = torch.empty((sample_count, chunk_count * k), dtype=torch.float32, device=device)
    launch_knn_sample(points_wp, to_warp(sample_ids), chunk_size, to_warp(partial), k=k)
    if chunk_count == 1:
        kth = partial[:, effective_k - 1]
    else:
        kth = partial.topk(effective_k, dim=1, largest=False).values[:, effective_k - 1]
    return kth.median()


def _grid_dims(extent_cells: list[int], cell_budget: int) -> list[int]:
    """Hash-grid dimensions: the bounding box in cells, halved along the longest axis until within budget."""
    dims = [max(1, int(n)) for n in extent_cells]
    while dims[0] * dims[1] * dims[2] > cell_budget:
        axis = int(np.argmax(dims))
        dims[axis] = (dims[axis] + 1) // 2
    return dims
