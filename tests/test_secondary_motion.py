"""SMAD's graph for the training instants: downsampling, binding, blending, frame matching, losses, files."""

import pytest
import torch

from warpavatar import ops
from warpavatar.extensions.graph import voxel_downsample
from warpavatar.extensions.secondary_motion import SecondaryMotion


def _random_rigid_poses(frame_count, joint_count, generator):
    poses = torch.eye(4).repeat(frame_count, joint_count, 1, 1)
    for t in range(frame_count):
        for j in range(joint_count):
            q, _ = torch.linalg.qr(torch.randn(3, 3, generator=generator))
            poses[t, j, :3, :3] = q * torch.sign(torch.det(q))
            poses[t, j, :3, 3] = torch.randn(3, generator=generator) * 0.3
    return poses


def _module(device, *, node_count=40, frame_count=5, joint_count=3, seed=0):
    generator = torch.Generator().manual_seed(seed)
    nodes = torch.rand(node_count, 3, generator=generator)
    poses = _random_rigid_poses(frame_count, joint_count, generator)
    module = SecondaryMotion(nodes.to(device), poses.to(device), voxel_size=0.2, neighbors=6, bind_count=4)
    with torch.no_grad():
        module.displacement.copy_(torch.randn(frame_count, node_count, 3, generator=generator).to(device) * 0.05)
    return module, poses.to(device), generator


def test_voxel_downsample_means_per_voxel(device):
    points = torch.tensor([[0.01, 0.01, 0.01], [0.09, 0.05, 0.02], [0.51, 0.02, 0.03], [0.55, 0.08, 0.01]],
                          device=device)
    nodes = voxel_downsample(points, 0.1)
    expected = torch.stack([points[:2].mean(0), points[2:].mean(0)])
    assert nodes.shape == (2, 3)
    assert torch.allclose(nodes, expected, atol=1e-6)
    # independent of row order
    assert torch.allclose(voxel_downsample(points.flip(0), 0.1), expected, atol=1e-6)


def test_graph_edges_are_the_knn_of_the_nodes(device):
    module, _, _ = _module(device)
    index, _ = ops.knn_graph(module.nodes, 6)
    assert module.edges.shape == (module.node_count * 6, 2)
    assert torch.equal(module.edges[:, 1].long().reshape(-1, 6), index)
    rest = module.nodes[module.edges[:, 0].long()] - module.nodes[module.edges[:, 1].long()]
    assert torch.allclose(module.rest_offset, rest)


def test_blend_matches_dense_reference_forward_and_gradient(device):
    module, poses, generator = _module(device)
    means = torch.rand(300, 3, generator=generator).to(device)
    values = torch.randn(module.node_count, 3, generator=generator).to(device).requires_grad_(True)
    out = module.gaussian_displacement(means, values)
    # dense reference: the 4 nearest nodes, Gaussian kernel on squared distance, normalized
    distance_sq = torch.cdist(means, module.nodes).square()
    nearest_sq, nearest = torch.topk(distance_sq, 4, dim=1, largest=False)
    kernel = torch.exp(-(nearest_sq - nearest_sq[:, :1]) / (2 * 0.2**2))
    weights = kernel / kernel.sum(1, keepdim=True)
    reference_values = values.detach().clone().requires_grad_(True)
    reference = (weights[:, :, None] * reference_values[nearest]).sum(1)
    assert torch.allclose(out, reference, atol=1e-5)
    upstream = torch.randn(out.shape, generator=generator).to(device)
    (out * upstream).sum().backward()
    (reference * upstream).sum().backward()
    assert torch.allclose(values.grad, reference_values.grad, atol=1e-5)


def test_blend_gradient_is_deterministic(device):
    """Bit-identical gradients on the CPU (a plain gather's backward is not there); on CUDA the sparse product may
    differ in the last bits between runs, like every atomic reduction on a GPU, so it is only held close."""
    module, _, generator = _module(device, node_count=300)
    means = torch.rand(50000, 3, generator=generator).to(device)
    upstream = torch.randn(50000, 3, generator=generator).to(device)
    grads = []
    for _ in range(3):
        values = torch.zeros(module.node_count, 3, device=device, requires_grad=True)
        (module.gaussian_displacement(means, values) * upstream).sum().backward()
        grads.append(values.grad)
    if torch.device(device).type == "cpu":
        assert all(torch.equal(grads[0], g) for g in grads[1:])
    else:
        assert all(torch.allclose(grads[0], g, rtol=1e-5, atol=1e-5) for g in grads[1:])


def test_frame_match_picks_the_training_instant_or_nothing(device):
    module, poses, _ = _module(device)
    for t in range(module.frame_count):
        assert torch.equal(module.node_displacement(poses[t]), module.displacement[t])
    other = poses[2].clone()
    other[1, 0, 3] += 0.01  # any other pose gets no displacement
    assert torch.count_nonzero(module.node_displacement(other)) == 0


def test_isometry_is_zero_for_a_translation_and_positive_for_a_stretch(device):
    module, _, _ = _module(device)
    shift = torch.tensor([0.3, -0.1, 0.2], device=device).expand(module.node_count, 3)
    assert float(module.isometry(shift)) < 1e-8
    stretch = module.nodes * 0.2  # scales the graph by 1.2
    value = float(module.isometry(stretch))
    lengths = module.rest_offset.norm(dim=-1)
    expected = float(((0.2 * lengths) ** 2).mean()) / 0.2**2
    assert value == pytest.approx(expected, rel=1e-4)


def test_regularizers_touch_only_the_frame_and_its_neighbours(device):
    module, _, _ = _module(device, frame_count=6)
    (module.damping(2) + module.magnitude(2)).backward()
    touched = module.displacement.grad.abs().amax(dim=(1, 2)) > 0
    assert touched.tolist() == [False, True, True, True, False, False]
    velocity = (module.displacement[1:4] - module.displacement[0:3])[1:] / 0.2
    assert float(module.damping(2).detach()) == pytest.approx(float(velocity.detach().square().sum(-1).mean()), rel=1e-5)
    module.sparsify_gradient()
    assert module.displacement.grad.is_sparse
    assert sorted(module.displacement.grad.coalesce().indices()[0].tolist()) == [1, 2, 3]


def test_file_state_round_trip_keeps_binding_and_values(device):
    module, poses, generator = _module(device)
    means = torch.rand(100, 3, generator=generator).to(device)
    module.bind(means)
    moved = means + 0.3  # a reload must use the saved binding, not rebind from moved Gaussians
    state = module.state_for_file()
    loaded = SecondaryMotion.from_file_state(state, device=device)
    for t in range(module.frame_count):
        a = module.gaussian_displacement(moved, module.node_displacement(poses[t]))
        b = loaded.gaussian_displacement(moved, loaded.node_displacement(poses[t]))
        assert torch.equal(a, b)
