"""Rotations of the cloth's nodes, and the garment Gaussians that ride on them.

Each node's rotation is the rotational part of its neighbourhood's deformation: with ``P_e = X_j - X_i`` the
rest offsets to its neighbours and ``Q_e = x_j - x_i`` the current ones, the rotation ``R`` closest to
``A = sum_e Q_e P_e^T`` (the polar factor: the ``R`` maximizing ``trace(R^T A)``). It is found by the fixed-point
iteration of Mueller et al. (2016, "A robust method to extract the rotational part of deformations"): from a
quaternion ``q`` (warm-started from the last frame's), with ``r_k`` the columns of ``R(q)`` and ``a_k`` those
of ``A``, the update ``omega = sum_k r_k x a_k / (|sum_k r_k . a_k| + eps)`` is a small rotation applied on the
left. That step only scales the gradient by a number, which converges slowly for the flat, elongated
neighbourhoods of cloth; where the second-order model of ``trace(R^T A)`` is concave (near the optimum of
any neighbourhood that is not a line) the full Newton step with its 3x3 Hessian is taken instead, which
converges quadratically (see ``_rotation_step``). Each step is a smooth function of its inputs (the small
rotation is the quaternion ``(1, omega / 2)`` normalized; the choice between the two steps changes only far
from the answer), so a few unrolled iterations differentiate cleanly, where an SVD's gradient blows up at
repeated singular values (flat or collapsed neighbourhoods, which cloth has).

A Gaussian riding on a node keeps its rest offset and rotation in the node's frame: its centre is
``x_node + R offset`` and its rotation ``q_node * q_rest`` (quaternions (w, x, y, z)).
"""

from __future__ import annotations

import torch

from warpavatar.geometry import quat_from_vector, quat_multiply, quat_rotate, quat_to_matrix

__all__ = ["node_rotations", "nearest_nodes", "ride_on_nodes"]


def node_rotations(
    rest_positions: torch.Tensor,
    positions: torch.Tensor,
    edges: torch.Tensor,
    *,
    initial: torch.Tensor | None = None,
    iterations: int = 4,
) -> torch.Tensor:
    """The rotation of every node's neighbourhood from the rest shape to the current one.

    Args:
        rest_positions: node positions in the rest shape [world units], float ``[M, 3]``.
        positions: current node positions [world units], float ``[M, 3]`` (differentiable).
        edges: (node, neighbour) ids, integer ``[E, 2]``: the neighbourhood of node ``i`` is every row
            ``(i, j)`` (give both directions of a symmetric graph).
        initial: warm start, unit quaternions ``[M, 4]`` (the previous frame's result); None: identity.
        iterations: iterations; near the answer each one squares the error (a warm start from the last frame
            needs few); from the identity, 12 recovered rotations up to 120 degrees in the tests, 20 up to 150,
            30 up to 170.

    Returns:
        Unit quaternions (w, x, y, z) ``[M, 4]``, differentiable with respect to ``positions``, ``initial``
        and ``rest_positions``. A node without neighbours keeps its warm start.
    """
    if positions.shape != rest_positions.shape or positions.dim() != 2 or positions.shape[1] != 3:
        raise ValueError(f"positions and rest_positions must both have shape [M, 3], got "
                         f"{list(positions.shape)} and {list(rest_positions.shape)}")
    if edges.dim() != 2 or edges.shape[1] != 2:
        raise ValueError(f"edges must have shape [E, 2], got {list(edges.shape)}")
    node_count = positions.shape[0]
    node, neighbour = edges[:, 0].long(), edges[:, 1].long()
    rest_offset = rest_positions[neighbour] - rest_positions[node]
    offset = positions[neighbour] - positions[node]
    # A_i = sum_e Q_e P_e^T, scaled by the rest edge length^2 so the update's size does not depend on units
    scale = (rest_offset * rest_offset).sum(-1).mean().clamp_min(1e-30)
    outer = (offset[:, :, None] * rest_offset[:, None, :]) / scale
    covariance = positions.new_zeros(node_count, 3, 3).index_add(0, node, outer.to(positions.dtype))
    if initial is None:
        quats = positions.new_zeros(node_count, 4)
        quats[:, 0] = 1.0
    else:
        quats = initial / initial.norm(dim=-1, keepdim=True)
    identity = torch.eye(3, dtype=positions.dtype, device=positions.device)
    for _ in range(iterations):
        quats = quat_multiply(quat_from_vector(0.5 * _rotation_step(quat_to_matrix(quats), covariance, identity)),
                              quats)
        quats = quats / quats.norm(dim=-1, keepdim=True)
    return quats


def _rotation_step(rotation: torch.Tensor, covariance: torch.Tensor, identity: torch.Tensor) -> torch.Tensor:
    """The small rotation ``omega [M, 3]`` (applied on the left) that increases ``trace(R^T A)``.

    To second order in ``omega``, ``trace((exp([omega]) R)^T A) = f + g . omega - omega^T H omega / 2`` with
    ``g = sum_k r_k x a_k``, ``B = A R^T`` and ``H = trace(B) I - sym(B)``: the Newton step is ``H^-1 g``
    where ``H`` is positive definite (always near the optimum of a neighbourhood that is not collinear), and
    the fixed-point step ``g / |trace(B)|`` of Mueller et al. elsewhere.
    """
    gradient = torch.cross(rotation, covariance, dim=1).sum(dim=2)  # sum_k r_k x a_k (columns)
    b = covariance @ rotation.transpose(1, 2)
    trace = b.diagonal(dim1=1, dim2=2).sum(-1)
    hessian = trace[:, None, None] * identity - 0.5 * (b + b.transpose(1, 2))
    # positive definite by Sylvester's criterion, with a margin relative to the neighbourhood's size
    margin = 1e-6 * trace.abs()
    minor2 = hessian[:, 0, 0] * hessian[:, 1, 1] - hessian[:, 0, 1] * hessian[:, 1, 0]
    adjugate, determinant = _adjugate_and_determinant(hessian)
    definite = (hessian[:, 0, 0] > margin) & (minor2 > margin**2) & (determinant > margin**3)
    # H^-1 g = adj(H) g / det(H), in closed form: torch.linalg.solve checks its input on the host (a device
    # synchronization per call on CUDA) and would need the identity substituted where H is not definite
    safe_determinant = torch.where(definite, determinant, torch.ones_like(determinant))
    newton = (adjugate @ gradient[:, :, None])[:, :, 0] / safe_determinant[:, None]
    fixed_point = gradient / (trace.abs()[:, None] + 1e-9)
    return torch.where(definite[:, None], newton, fixed_point)


def _adjugate_and_determinant(matrix: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Adjugate ``[M, 3, 3]`` and determinant ``[M]`` of 3x3 matrices ``[M, 3, 3]``, element-wise (no host
    synchronization, differentiable): ``matrix @ adjugate = determinant * I``."""
    rows = matrix.unbind(dim=1)
    # the adjugate's columns are the cross products of the matrix's rows (row 1 x row 2, row 2 x row 0, ...)
    columns = [torch.cross(rows[(k + 1) % 3], rows[(k + 2) % 3], dim=1) for k in range(3)]
    adjugate = torch.stack(columns, dim=2)
    determinant = (rows[0] * columns[0]).sum(dim=1)
    return adjugate, determinant


def nearest_nodes(points: torch.Tensor, nodes: torch.Tensor, *, chunk: int = 4096) -> torch.Tensor:
    """Id of the nearest node of each point: ``points [G, 3]``, ``nodes [M, 3]`` -> int64 ``[G]``."""
    if nodes.shape[0] == 0:
        raise ValueError("nearest_nodes needs at least one node")
    parts = [torch.cdist(points[start:start + chunk].float(), nodes.float()).argmin(dim=1)
             for start in range(0, points.shape[0], chunk)]
    return torch.cat(parts) if parts else torch.zeros(0, dtype=torch.int64, device=points.device)


def ride_on_nodes(
    node_positions: torch.Tensor,
    node_quats: torch.Tensor,
    anchor: torch.Tensor,
    rest_offset: torch.Tensor,
    rest_quats: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Centres and rotations of Gaussians carried by nodes.

    Args:
        node_positions: current node positions [world units], ``[M, 3]``.
        node_quats: node rotations from the rest shape (:func:`node_rotations`), unit (w, x, y, z) ``[M, 4]``.
        anchor: the node each Gaussian rides on, integer ``[G]`` (e.g. :func:`nearest_nodes` in the rest shape).
        rest_offset: each Gaussian's rest centre minus its node's rest position [world units], ``[G, 3]``.
        rest_quats: each Gaussian's rest rotation, (w, x, y, z) ``[G, 4]``.

    Returns:
        ``(means [G, 3], quats [G, 4])``: ``x_node + R_node offset`` and ``q_node * q_rest``; differentiable.
    """
    anchor = anchor.long()
    quats = node_quats[anchor]
    return node_positions[anchor] + quat_rotate(quats, rest_offset), quat_multiply(quats, rest_quats)
