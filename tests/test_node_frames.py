"""Tests of :mod:`warpavatar.sim.node_frames`: node rotations from neighbourhood deformation, Gaussians riding on
nodes."""

import math

import torch

from warpavatar import ops
from warpavatar.geometry import quat_multiply, quat_to_matrix
from warpavatar.sim import nearest_nodes, node_rotations, ride_on_nodes


def cloth_patch(seed, count=60, *, dtype=torch.float32):
    """A nearly flat patch of nodes (as cloth is) and its symmetric 6-NN edges (both directions)."""
    generator = torch.Generator().manual_seed(seed)
    points = torch.rand(count, 3, generator=generator) * torch.tensor([0.3, 0.3, 0.003])
    index, _ = ops.knn_graph(points, 6)
    edges = torch.stack([torch.arange(count).repeat_interleave(6), index.reshape(-1)], dim=1)
    edges = torch.unique(torch.cat([edges, edges.flip(1)]), dim=0)
    return points.to(dtype), edges


def rotation(angle_degrees, axis):
    axis = torch.as_tensor(axis, dtype=torch.float64)
    axis = axis / axis.norm()
    half = math.radians(angle_degrees) / 2
    return torch.cat([torch.tensor([math.cos(half)], dtype=torch.float64), math.sin(half) * axis])


def same_rotation(quats, quat, atol):
    """Every row of ``quats [M,4]`` is the rotation ``quat [4]`` (either sign)."""
    matrices = quat_to_matrix(quats.double())
    expected = quat_to_matrix(quat.double())
    return (matrices - expected).abs().max().item() < atol


def test_a_rigidly_rotated_graph_recovers_its_rotation():
    rest, edges = cloth_patch(0)
    for angle, axis, iterations in ((20, (0, 0, 1), 6), (120, (1, -2, 0.5), 12), (150, (0.3, 1, 0), 20)):
        quat = rotation(angle, axis)
        moved = rest @ quat_to_matrix(quat).float().T + torch.tensor([0.4, -1.0, 2.0])
        quats = node_rotations(rest, moved, edges, iterations=iterations)
        assert same_rotation(quats, quat, 1e-5), angle
        assert torch.allclose(quats.norm(dim=1), torch.ones(len(quats)))
    # warm-started from the last frame, a few iterations follow the next one
    previous = rotation(120, (1, -2, 0.5))
    step = quat_multiply(rotation(8, (0, 1, 1)), previous)
    moved = rest @ quat_to_matrix(step).float().T
    quats = node_rotations(rest, moved, edges, initial=previous.float().expand(len(rest), 4), iterations=3)
    assert same_rotation(quats, step, 1e-5)


def test_gradients_match_finite_differences():
    # float64, a non-rigid deformation with a warm start: torch autograd through the unrolled iterations
    # against central differences (torch.autograd.gradcheck).
    rest, edges = cloth_patch(1, count=14, dtype=torch.float64)
    generator = torch.Generator().manual_seed(2)
    quat = rotation(40, (1, 1, 0))
    moved = rest @ quat_to_matrix(quat).T + 0.02 * torch.randn(rest.shape, generator=generator, dtype=torch.float64)
    initial = rotation(30, (1, 0.8, 0.1)).expand(len(rest), 4).clone()
    weights = torch.randn(len(rest), 4, generator=generator, dtype=torch.float64)

    def loss(positions, warm_start):
        return (node_rotations(rest, positions, edges, initial=warm_start, iterations=4) * weights).sum()

    assert torch.autograd.gradcheck(loss, (moved.requires_grad_(), initial.requires_grad_()), eps=1e-6, atol=1e-6,
                                    fast_mode=True)
    # the check has teeth: a gradient of the wrong sign is caught by the same comparison
    analytic = torch.autograd.grad(loss(moved, initial), moved)[0]
    element = analytic.abs().argmax()
    plus, minus = moved.detach().clone(), moved.detach().clone()
    plus.view(-1)[element] += 1e-6
    minus.view(-1)[element] -= 1e-6
    numeric = (loss(plus, initial) - loss(minus, initial)).item() / 2e-6
    assert abs(analytic.view(-1)[element].item() - numeric) < 1e-5 * abs(numeric)
    assert abs(-analytic.view(-1)[element].item() - numeric) > 1e-5 * abs(numeric)


def test_degenerate_neighbourhoods_stay_finite():
    # a collinear neighbourhood, a collapsed one and a node without neighbours
    rest = torch.tensor([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.2, 0.0, 0.0], [1.0, 1.0, 1.0]], requires_grad=True)
    positions = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.1, 0.0], [0.0, 0.0, 0.0], [1.0, 1.0, 1.0]],
                             requires_grad=True)
    edges = torch.tensor([[0, 1], [1, 0], [1, 2], [2, 1], [0, 2], [2, 0]])
    initial = rotation(10, (0, 0, 1)).float().expand(4, 4)
    quats = node_rotations(rest, positions, edges, initial=initial, iterations=6)
    assert torch.isfinite(quats).all()
    torch.testing.assert_close(quats[3], initial[3])
    grads = torch.autograd.grad(quats.sum(), [rest, positions])
    assert all(torch.isfinite(g).all() for g in grads)


def test_gaussians_ride_rigidly_with_their_nodes():
    rest, edges = cloth_patch(3)
    generator = torch.Generator().manual_seed(4)
    gaussian_means = rest[torch.randint(0, len(rest), (200,), generator=generator)] + 0.01 * torch.randn(
        200, 3, generator=generator)
    gaussian_quats = torch.randn(200, 4, generator=generator)
    gaussian_quats = gaussian_quats / gaussian_quats.norm(dim=1, keepdim=True)
    anchor = nearest_nodes(gaussian_means, rest)
    assert torch.equal(anchor, torch.cdist(gaussian_means, rest).argmin(dim=1))
    offset = gaussian_means - rest[anchor]
    quat = rotation(70, (0.2, -1, 0.4))
    matrix = quat_to_matrix(quat).float()
    translation = torch.tensor([0.5, 0.1, -0.3])
    moved = rest @ matrix.T + translation
    node_quats = node_rotations(rest, moved, edges, iterations=10)
    means, quats = ride_on_nodes(moved, node_quats, anchor, offset, gaussian_quats)
    torch.testing.assert_close(means, gaussian_means @ matrix.T + translation, rtol=0, atol=1e-5)
    torch.testing.assert_close(quat_to_matrix(quats), matrix @ quat_to_matrix(gaussian_quats), rtol=0, atol=1e-5)
