"""Plain-torch references of :func:`warpavatar.ops.spring_step`, ``isometry_loss`` and ``damping_loss``.

Same signatures and conventions as the Warp ops (see :mod:`warpavatar._src.springs`), differentiated by torch
autograd, and dtype-generic: the tests run them in float64 for finite differences.
"""

from __future__ import annotations

import torch

__all__ = ["spring_step", "isometry_loss", "damping_loss"]


def _valid_edges(edges: torch.Tensor, node_count: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Mask of edges with both ids in ``[0, M)`` and their receiver and sender ids (int64)."""
    edges = edges.long()
    valid = ((edges >= 0) & (edges < node_count)).all(dim=1)
    return valid, edges[valid, 0], edges[valid, 1]


def spring_step(x, v, edges, rest_offset, stiffness, damping, mass, force, dt: float
                ) -> tuple[torch.Tensor, torch.Tensor]:
    """Semi-implicit Euler step: ``a = (F - gamma v - sum_e k_e (x_i - x_j - L_e)) / m``, ``v' = v + dt a``,
    ``x' = x + dt v'``; returns ``(x_next [M, 3], v_next [M, 3])``."""
    valid, receiver, sender = _valid_edges(edges, x.shape[0])
    springs = stiffness[valid, None] * (x[receiver] - x[sender] - rest_offset[valid])
    spring_force_sum = torch.zeros_like(x).index_add(0, receiver, springs)
    acceleration = (force - damping[:, None] * v - spring_force_sum) / mass[:, None]
    v_next = v + dt * acceleration
    x_next = x + dt * v_next
    return x_next, v_next


def isometry_loss(x: torch.Tensor, edges: torch.Tensor, rest_offset: torch.Tensor) -> torch.Tensor:
    """Mean over valid edges of ``(|x_i - x_j| - |L_e|)^2`` (0 without valid edges)."""
    valid, receiver, sender = _valid_edges(edges, x.shape[0])
    residual = (x[receiver] - x[sender]).norm(dim=1) - rest_offset[valid].norm(dim=1)
    return (residual * residual).sum() / max(int(valid.sum()), 1)


def damping_loss(velocity: torch.Tensor) -> torch.Tensor:
    """Mean over velocity vectors (all leading dimensions) of ``|v|^2`` (0 for empty input)."""
    flat = velocity.reshape(-1, 3)
    return (flat * flat).sum() / max(flat.shape[0], 1)
