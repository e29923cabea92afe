"""Brute-force torch reference of :func:`warpavatar.ops.knn_graph` (same signature and conventions)."""

from __future__ import annotations

import math

import torch

__all__ = ["knn_graph"]

_ROWS_PER_CHUNK = 4096
"""Query rows per ``cdist`` block (memory: ``_ROWS_PER_CHUNK * M`` floats)."""


def knn_graph(
    points: torch.Tensor, k: int, *, max_radius: float | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Exact k nearest other points by all pairwise distances (``torch.cdist`` + ``topk``), in row chunks.

    Args:
        points: positions, float ``[M, 3]``; computed in float32 like the Warp op.
        k: neighbours per point, ``>= 1``.
        max_radius: keep only neighbours at distance ``<= max_radius`` (``None``: no limit).

    Returns:
        ``(index int64 [M, k], distance float32 [M, k])``, nearest first; ``-1`` / ``inf`` padding.
        Differences are exact float32 (``cdist`` without the matrix-product shortcut), so distances match the
        Warp op up to float32 rounding of the sum of squares.
    """
    if k < 1:
        raise ValueError(f"k must be >= 1, got {k}")
    positions = points.detach().to(torch.float32)
    point_count = positions.shape[0]
    device = positions.device
    index = torch.full((point_count, k), -1, dtype=torch.int64, device=device)
    distance = torch.full((point_count, k), math.inf, dtype=torch.float32, device=device)
    take = min(k, point_count)
    for start in range(0, point_count, _ROWS_PER_CHUNK):
        rows = positions[start : start + _ROWS_PER_CHUNK]
        block = torch.cdist(rows, positions, compute_mode="donot_use_mm_for_euclid_dist")
        own = torch.arange(start, start + rows.shape[0], device=device)
        block[torch.arange(rows.shape[0], device=device), own] = math.inf
        if max_radius is not None:
            block = block.masked_fill(block > max_radius, math.inf)
        values, columns = block.topk(take, dim=1, largest=False)
        columns = columns.masked_fill(torch.isinf(values), -1)
        index[start : start + rows.shape[0], :take] = columns
        distance[start : start + rows.shape[0], :take] = values
    return index, distance
