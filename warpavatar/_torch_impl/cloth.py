"""Plain-torch reference of :func:`warpavatar.ops.cloth_edge_terms` (dtype-generic: float64 for finite
differences), with the conventions of :mod:`warpavatar.kernels.cloth`."""

from __future__ import annotations

import torch

__all__ = ["cloth_edge_terms"]


def cloth_edge_terms(x, v, edges, rest_length, edge_damping) -> tuple[torch.Tensor, torch.Tensor]:
    """``(min(L, 2|d|) d / |d| [E, 3], -sum_e c_e (v_i - v_j) [M, 3])`` over valid edges (see the Warp op)."""
    edges = edges.long()
    node_count = x.shape[0]
    valid = ((edges >= 0) & (edges < node_count)).all(dim=1)
    receiver, sender = edges[:, 0].clamp(0, max(node_count - 1, 0)), edges[:, 1].clamp(0, max(node_count - 1, 0))
    if node_count == 0:
        return x.new_zeros(edges.shape[0], 3), x.new_zeros(0, 3)
    delta = x[receiver] - x[sender]
    length = delta.norm(dim=1)
    long_enough = valid & (length > 1e-12)
    # (torch.where keeps the clamped side's gradient at the kink L = 2 l, as the kernel does)
    effective = torch.where(rest_length < 2.0 * length, rest_length, 2.0 * length)
    scale = torch.where(long_enough, effective / torch.where(long_enough, length, torch.ones_like(length)),
                        torch.zeros_like(length))
    rest_offset = scale[:, None] * delta
    relative = torch.where(valid[:, None], v[receiver] - v[sender], torch.zeros_like(delta))
    damping_force = torch.zeros_like(x).index_add(0, receiver, -edge_damping[:, None] * relative)
    return rest_offset, damping_force
