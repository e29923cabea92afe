"""Warp kernels of the exact k-nearest-neighbour graph (the Gaussian graph of SMAD, Sec. 3.1).

Two kernels, both specialized at compile time for the neighbour count ``k`` (one small Warp module per ``k``,
built on first use), so that the sorted candidate list of each query lives in registers:

* ``knn_sample``: exact k-th neighbour distance of a few sample points by brute force, split over chunks of
  the point set; the bridge takes the median of them to choose the hash-grid cell width.
* ``knn_query``: one thread per query point. The query scans rings of cells of a :class:`warp.HashGrid`
  around its own cell (ring 0 is the cell itself, ring ``r`` the cells at Chebyshev distance ``r``), keeps the
  ``k`` best candidates in a sorted list, skips cells farther than the current k-th best distance, and stops
  as soon as the k-th best distance is certified: every point outside the scanned block of cells is at least
  as far. A query that is not certified after ``ring_limit`` rings is appended to a list of unfinished
  queries; the bridge runs those again on a coarser grid, until the scanned block covers every point.

Conventions shared by the kernels and the bridge (:mod:`warpavatar._src.knn`):
    * the grid is built over *centred* points (``points - centre``), which keeps cell coordinates small and
      float rounding of cell membership below ``slack`` (world units); distances are always computed from
      the original points, so they are the plain float32 Euclidean distances;
    * cells are indexed by world cell coordinates ``floor(p * cell_width_inv)`` exactly as
      :class:`warp.HashGrid` bins points; ``lo_cell``/``hi_cell`` bound the cells of all points, cells
      outside are known to be empty and never visited;
    * the hash grid may have fewer cells than the bounding box (cells then alias modulo the grid
      dimensions); when a search block may grow wider than ``alias_dim`` cells it could meet one physical
      cell twice, so candidates are then filtered by their own world cell.
"""

from __future__ import annotations

import functools

import numpy as np
import warp as wp

from warpavatar.kernels.launch import launch

__all__ = [
    "MAX_K",
    "cell_width_inverse",
    "knn_kernels",
    "launch_knn_sample",
    "launch_knn_query",
]

MAX_K = 64
"""Largest neighbour count with a specialized kernel (the sorted list of k distances and k indices is kept
in registers; beyond this it would spill)."""


def cell_width_inverse(cell_width: float) -> float:
    """``1 / cell_width`` rounded as :class:`warp.HashGrid` rounds it (float32), so host and kernels bin alike."""
    return float(np.float32(1.0) / np.float32(cell_width))


@wp.func
def world_cell(p: wp.vec3, cell_width_inv: float):
    """World cell coordinates of a (centred) point, binned exactly as :class:`warp.HashGrid` bins it."""
    return wp.vec3i(
        int(wp.floor(p[0] * cell_width_inv)),
        int(wp.floor(p[1] * cell_width_inv)),
        int(wp.floor(p[2] * cell_width_inv)),
    )


@wp.func
def cell_gap_sq(p: wp.vec3, cell: wp.vec3i, cell_width: float, slack: float):
    """Squared distance from ``p`` to the box of ``cell``, shrunk by ``slack`` per axis (a lower bound)."""
    gap_sq = float(0.0)
    for axis in range(3):
        lower = float(cell[axis]) * cell_width
        upper = lower + cell_width
        gap = wp.max(wp.max(lower - p[axis], p[axis] - upper) - slack, 0.0)
        gap_sq += gap * gap
    return gap_sq


@wp.func
def certified_radius(
    p: wp.vec3,
    cell: wp.vec3i,
    ring: int,
    cell_width: float,
    slack: float,
    lo_cell: wp.vec3i,
    hi_cell: wp.vec3i,
):
    """Radius around ``p`` inside which every point has been seen after scanning rings ``0..ring``.

    The scanned block is the cells ``cell - ring .. cell + ring``; a side of the block beyond which no cell
    holds points (outside ``lo_cell..hi_cell``) does not limit the radius, so the result is ``inf`` once the
    block covers all points.
    """
    radius = float(wp.inf)
    for axis in range(3):
        if cell[axis] - ring > lo_cell[axis]:
            radius = wp.min(radius, p[axis] - float(cell[axis] - ring) * cell_width)
        if cell[axis] + ring < hi_cell[axis]:
            radius = wp.min(radius, float(cell[axis] + ring + 1) * cell_width - p[axis])
    return wp.max(radius - slack, 0.0)


@functools.lru_cache(maxsize=None)
def knn_kernels(k: int):
    """The ``(knn_sample, knn_query)`` kernels specialized for ``k`` neighbours, ``1 <= k <= MAX_K``.

    Each ``k`` gets its own Warp module, compiled on first launch and cached on disk by Warp.
    """
    if not 1 <= k <= MAX_K:
        raise ValueError(f"k must be in [1, {MAX_K}], got {k}")
    neighbour_count = k
    last = k - 1
    distance_list = wp.types.vector(length=k, dtype=wp.float32)
    index_list = wp.types.vector(length=k, dtype=wp.int32)
    module = f"warpavatar_knn_k{k}"

    @wp.kernel(enable_backward=False, module=module)
    def knn_sample(
        points: wp.array(dtype=wp.vec3),
        sample_ids: wp.array(dtype=wp.int32),
        chunk_size: int,
        partial_distance_sq: wp.array2d(dtype=wp.float32),
    ):
        # Thread (c, s): the k smallest squared distances from sample s to the points of chunk c. Samples vary
        # fastest, so the threads of a warp read the same point at the same time (one broadcast load).
        chunk, sample = wp.tid()
        i = sample_ids[sample]
        p = points[i]
        begin = chunk * chunk_size
        end = wp.min(begin + chunk_size, points.shape[0])
        best = distance_list()
        for n in range(wp.static(neighbour_count)):
            best[n] = wp.inf
        for j in range(begin, end):
            if j != i:
                candidate = wp.length_sq(points[j] - p)
                if candidate < best[wp.static(last)]:
                    for n in range(wp.static(neighbour_count)):
                        swap = candidate < best[n]
                        previous = best[n]
                        best[n] = wp.where(swap, candidate, previous)
                        candidate = wp.where(swap, previous, candidate)
        for n in range(wp.static(neighbour_count)):
            partial_distance_sq[sample, chunk * wp.static(neighbour_count) + n] = best[n]

    @wp.kernel(enable_backward=False, module=module)
    def knn_query(
        grid: wp.uint64,
        points: wp.array(dtype=wp.vec3),
        grid_points: wp.array(dtype=wp.vec3),
        query_ids: wp.array(dtype=wp.int32),
        use_grid_order: int,
        cell_width: float,
        cell_width_inv: float,
        slack: float,
        lo_cell: wp.vec3i,
        hi_cell: wp.vec3i,
        ring_limit: int,
        alias_dim: int,
        max_distance_sq: float,
        out_index: wp.array2d(dtype=wp.int64),
        out_distance: wp.array2d(dtype=wp.float32),
        unfinished_ids: wp.array(dtype=wp.int32),
        unfinished_count: wp.array(dtype=wp.int32),
    ):
        tid = wp.tid()
        i = int(0)
        if use_grid_order != 0:
            # Walk the queries in the grid's cell order: neighbouring threads read neighbouring cells.
            i = wp.hash_grid_point_id(grid, tid)
        else:
            i = query_ids[tid]
        p = points[i]
        p_grid = grid_points[i]
        home = world_cell(p_grid, cell_width_inv)

        # Sorted list of the best squared distances so far; empty slots hold the acceptance threshold.
        best_distance = distance_list()
        best_index = index_list()
        for n in range(wp.static(neighbour_count)):
            best_distance[n] = max_distance_sq
            best_index[n] = -1

        # Once the scanned block may be wider than the grid along an aliased axis, one physical cell can be
        # met through two world cells: then only points of the visited world cell count, on every ring
        # (a foreign point taken early could otherwise come again through its own cell later).
        check_alias = 2 * ring_limit + 1 > alias_dim
        certified = bool(False)
        ring = int(0)
        while ring <= ring_limit:
            for dz in range(-ring, ring + 1):
                z = home[2] + dz
                if z < lo_cell[2] or z > hi_cell[2]:
                    continue
                for dy in range(-ring, ring + 1):
                    y = home[1] + dy
                    if y < lo_cell[1] or y > hi_cell[1]:
                        continue
                    # Rows inside the ring only touch it at both ends.
                    step = int(1)
                    if wp.abs(dz) != ring and wp.abs(dy) != ring:
                        step = 2 * ring
                    for dx in range(-ring, ring + 1, step):
                        x = home[0] + dx
                        if x < lo_cell[0] or x > hi_cell[0]:
                            continue
                        cell = wp.vec3i(x, y, z)
                        if cell_gap_sq(p_grid, cell, cell_width, slack) >= best_distance[wp.static(last)]:
                            continue
                        centre = wp.vec3(float(x) + 0.5, float(y) + 0.5, float(z) + 0.5) * cell_width
                        query = wp.hash_grid_query(grid, centre, 0.0)
                        j = int(0)
                        while wp.hash_grid_query_next(query, j):
                            if j == i:
                                continue
                            if check_alias:
                                other = world_cell(grid_points[j], cell_width_inv)
                                if other[0] != x or other[1] != y or other[2] != z:
                                    continue
                            candidate = wp.length_sq(points[j] - p)
                            if candidate < best_distance[wp.static(last)]:
                                candidate_index = j
                                for n in range(wp.static(neighbour_count)):
                                    swap = candidate < best_distance[n]
                                    previous = best_distance[n]
                                    previous_index = best_index[n]
                                    best_distance[n] = wp.where(swap, candidate, previous)
                                    best_index[n] = wp.where(swap, candidate_index, previous_index)
                                    candidate = wp.where(swap, previous, candidate)
                                    candidate_index = wp.where(swap, previous_index, candidate_index)
            radius = certified_radius(p_grid, home, ring, cell_width, slack, lo_cell, hi_cell)
            if best_distance[wp.static(last)] <= radius * radius:
                certified = True
                break
            ring += 1

        if certified:
            for n in range(wp.static(neighbour_count)):
                if best_index[n] >= 0:
                    out_index[i, n] = wp.int64(best_index[n])
                    out_distance[i, n] = wp.sqrt(best_distance[n])
                else:
                    out_index[i, n] = wp.int64(-1)
                    out_distance[i, n] = wp.inf
        else:
            slot = wp.atomic_add(unfinished_count, 0, 1)
            unfinished_ids[slot] = i

    return knn_sample, knn_query


def launch_knn_sample(
    points: wp.array,
    sample_ids: wp.array,
    chunk_size: int,
    partial_distance_sq: wp.array,
    *,
    k: int,
) -> None:
    """Brute-force k smallest squared distances of sample points, per chunk of the point set.

    Args:
        points: point positions, ``wp.vec3`` array of shape ``[M]``.
        sample_ids: indices of the sample points, int32 ``[S]``.
        chunk_size: points per chunk; ``C = ceil(M / chunk_size)`` chunks.
        partial_distance_sq: output, float32 ``[S, C * k]``: chunk ``c`` writes columns ``c*k .. c*k+k-1``
            (ascending; ``inf`` where a chunk has fewer than ``k`` other points).
        k: neighbour count (selects the specialized kernel).
    """
    sample_count = sample_ids.shape[0]
    point_count = points.shape[0]
    if sample_count == 0 or point_count == 0:
        return
    if chunk_size <= 0:
        raise ValueError(f"chunk_size must be positive, got {chunk_size}")
    chunk_count = (point_count + chunk_size - 1) // chunk_size
    if partial_distance_sq.shape != (sample_count, chunk_count * k):
        raise ValueError(
            f"partial_distance_sq must have shape {(sample_count, chunk_count * k)}, got {partial_distance_sq.shape}"
        )
    kernel, _ = knn_kernels(k)
    launch(
        kernel,
        dim=(chunk_count, sample_count),
        inputs=[points, sample_ids, chunk_size],
        outputs=[partial_distance_sq],
        device=points.device,
    )


def launch_knn_query(
    grid: wp.HashGrid,
    points: wp.array,
    grid_points: wp.array,
    query_ids: wp.array | None,
    query_count: int,
    *,
    k: int,
    cell_width: float,
    slack: float,
    lo_cell: tuple[int, int, int],
    hi_cell: tuple[int, int, int],
    ring_limit: int,
    alias_dim: int,
    max_distance_sq: float,
    out_index: wp.array,
    out_distance: wp.array,
    unfinished_ids: wp.array,
    unfinished_count: wp.array,
) -> None:
    """Ring search of ``query_count`` queries on a built hash grid.

    Args:
        grid: :class:`warp.HashGrid` built over ``grid_points`` with cell width ``cell_width``.
        points: original point positions (distances are measured on them), ``wp.vec3`` ``[M]``.
        grid_points: the centred positions the grid was built from, ``wp.vec3`` ``[M]``.
        query_ids: point indices to query, int32; ``None`` queries every point in the grid's sorted order
            (then ``query_count`` must be ``M``).
        query_count: number of queries (threads).
        k: neighbour count (selects the specialized kernel).
        cell_width: grid cell width [world units]; must be the float32 value the grid was built with.
        slack: bound on float rounding of cell membership [world units].
        lo_cell, hi_cell: smallest and largest world cell coordinates of any point, per axis.
        ring_limit: rings scanned before a query is handed to the next, coarser level.
        alias_dim: smallest grid dimension along an axis where cells alias (a large value when none do);
            candidates are filtered by world cell when ``2 * ring_limit + 1 > alias_dim``.
        max_distance_sq: acceptance threshold on squared distances (``inf`` when unbounded).
        out_index: int64 ``[M, k]``, rows of certified queries are written (``-1`` padding).
        out_distance: float32 ``[M, k]``, rows of certified queries are written (``inf`` padding).
        unfinished_ids: int32 ``[>= query_count]``, receives the queries left unfinished.
        unfinished_count: int32 ``[1]``, incremented once per unfinished query (must start at 0).
    """
    if query_count == 0:
        return
    point_count = points.shape[0]
    if grid_points.shape[0] != point_count:
        raise ValueError("points and grid_points must have the same length")
    if out_index.shape != (point_count, k) or out_distance.shape != (point_count, k):
        raise ValueError(f"out_index and out_distance must have shape {(point_count, k)}")
    if unfinished_ids.shape[0] < query_count or unfinished_count.shape[0] < 1:
        raise ValueError("unfinished_ids must hold query_count entries and unfinished_count one")
    use_grid_order = 1 if query_ids is None else 0
    if query_ids is None:
        if query_count != point_count:
            raise ValueError("querying in grid order requires query_count == number of points")
        query_ids = unfinished_ids  # unused by the kernel in this mode
    elif query_ids.shape[0] < query_count:
        raise ValueError("query_ids is shorter than query_count")
    cell_width = float(np.float32(cell_width))
    cell_width_inv = cell_width_inverse(cell_width)
    _, kernel = knn_kernels(k)
    launch(
        kernel,
        dim=query_count,
        inputs=[
            grid.id,
            points,
            grid_points,
            query_ids,
            use_grid_order,
            cell_width,
            cell_width_inv,
            float(slack),
            wp.vec3i(*lo_cell),
            wp.vec3i(*hi_cell),
            int(ring_limit),
            int(alias_dim),
            float(max_distance_sq),
        ],
        outputs=[out_index, out_distance, unfinished_ids, unfinished_count],
        device=points.device,
    )
