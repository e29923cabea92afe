"""k-NN graph benchmark: ``python tools/bench_kernels.py knn [--device cuda:0] [--quick]``.

For 40k, 200k and 1M points (``--quick``: 5k and 20k), uniform in a cube and surface-like (a noisy unit
sphere: points on a 2D manifold, as the Gaussian graph of an avatar), k = 16, it times:

* ``warpavatar``: :func:`warpavatar.ops.knn_graph` on the device, whole call (statistics, hash-grid builds,
  searches, host syncs), median of repeated calls, and torch's peak memory during one call;
* ``scipy cKDTree``: build + query of k+1 neighbours (the point itself comes first) with ``workers=-1``, on
  the host copy of the points (transfer not counted);
* ``torch brute force``: chunked ``torch.cdist`` (matrix-product mode) + ``topk`` on the device, only where
  it stays affordable (up to 200k points on CUDA, 10k on CPU).

Each row also reports ``max_dist_err``: the largest difference between warpavatar's and cKDTree's sorted
neighbour distances (a check that the exact search stays exact at scale). Target on an H100: 1M points,
k = 16, under 20 ms.
"""

from __future__ import annotations

import math
import time

import numpy as np
import torch

from bench_common import peak_memory_scope, time_function

from warpavatar import ops

__all__ = ["run"]

NEIGHBOURS = 16


def make_points(distribution: str, point_count: int, *, seed: int = 0) -> torch.Tensor:
    """Benchmark point clouds, float32 ``[point_count, 3]`` on the CPU.

    ``uniform``: uniform in the unit cube. ``surface``: uniform on the unit sphere with Gaussian noise of
    standard deviation 0.002 (surface-like, as avatar Gaussians).
    """
    generator = torch.Generator().manual_seed(seed)
    if distribution == "uniform":
        return torch.rand(point_count, 3, generator=generator)
    if distribution == "surface":
        points = torch.randn(point_count, 3, generator=generator)
        points = points / points.norm(dim=1, keepdim=True)
        return points + 0.002 * torch.randn(point_count, 3, generator=generator)
    raise ValueError(f"unknown distribution {distribution!r}")


def brute_force_knn(points: torch.Tensor, k: int, *, chunk_bytes: int = 2**28) -> tuple[torch.Tensor, torch.Tensor]:
    """k nearest other points by chunked ``cdist`` + ``topk`` (fast matrix-product distances)."""
    point_count = points.shape[0]
    rows_per_chunk = max(1, chunk_bytes // (4 * point_count))
    indices, distances = [], []
    for start in range(0, point_count, rows_per_chunk):
        rows = points[start : start + rows_per_chunk]
        block = torch.cdist(rows, points)
        block[torch.arange(rows.shape[0], device=points.device), torch.arange(start, start + rows.shape[0],
                                                                               device=points.device)] = math.inf
        values, columns = block.topk(k, dim=1, largest=False)
        indices.append(columns)
        distances.append(values)
    return torch.cat(indices), torch.cat(distances)


def _ckdtree_query(points_np: np.ndarray, k: int):
    from scipy.spatial import cKDTree

    tree = cKDTree(points_np)
    return tree.query(points_np, k=k + 1, workers=-1)


def run(device: str, quick: bool) -> list[dict]:
    """Benchmark rows (see the module docstring); one per size, distribution and method."""
    try:
        import scipy.spatial  # noqa: F401

        have_scipy = True
    except ImportError:
        have_scipy = False
    on_cuda = device.startswith("cuda")
    sizes = (5_000, 20_000) if quick else (40_000, 200_000, 1_000_000)
    if on_cuda:
        warmup, repeats = (1, 3) if quick else (3, 20)
    else:
        warmup, repeats = (1, 2) if quick else (1, 3)
    brute_force_limit = 200_000 if on_cuda else 10_000
    rows = []
    for point_count in sizes:
        for distribution in ("uniform", "surface"):
            host_points = make_points(distribution, point_count)
            points = host_points.to(device)
            ops.knn_graph(points, NEIGHBOURS)  # compile and warm up
            with peak_memory_scope(device) as memory:
                index, distance = ops.knn_graph(points, NEIGHBOURS)
            ours_ms = time_function(lambda: ops.knn_graph(points, NEIGHBOURS), device=device, warmup=warmup,
                                    repeats=repeats)
            base = {"points": point_count, "distribution": distribution, "k": NEIGHBOURS}

            ckdtree_ms = max_error = None
            if have_scipy:
                points_np = host_points.numpy()
                times = []
                for _ in range(1 if point_count >= 1_000_000 and not on_cuda else 3):
                    start = time.perf_counter()
                    tree_distance, _ = _ckdtree_query(points_np, NEIGHBOURS)
                    times.append((time.perf_counter() - start) * 1e3)
                ckdtree_ms = float(np.median(times))
                max_error = float(np.abs(tree_distance[:, 1:] - distance.cpu().numpy()).max())
            rows.append({**base, "method": "warpavatar knn_graph", "ms": ours_ms, "peak_MiB": memory.peak_mib,
                         "speedup_vs_ckdtree": (ckdtree_ms / ours_ms) if ckdtree_ms else None,
                         "max_dist_err": max_error})
            if ckdtree_ms is not None:
                rows.append({**base, "method": "scipy cKDTree (workers=-1, build+query)", "ms": ckdtree_ms,
                             "peak_MiB": None, "speedup_vs_ckdtree": 1.0, "max_dist_err": None})
            if point_count <= brute_force_limit:
                brute_ms = time_function(lambda: brute_force_knn(points, NEIGHBOURS), device=device,
                                         warmup=1, repeats=3 if not on_cuda else 5)
                rows.append({**base, "method": "torch brute force (cdist+topk)", "ms": brute_ms, "peak_MiB": None,
                             "speedup_vs_ckdtree": (ckdtree_ms / brute_ms) if ckdtree_ms else None,
                             "max_dist_err": None})
            del index, distance
    return rows
