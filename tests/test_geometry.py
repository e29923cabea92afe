"""The shared maths of warpavatar.geometry: quaternions (torch and numpy alike), pose matching, encodings, MLPs."""

import math

import numpy as np
import pytest
import torch

from warpavatar import geometry


def _random_quats(count, generator, dtype=torch.float64):
    quats = torch.randn(count, 4, generator=generator, dtype=dtype)
    return quats / quats.norm(dim=-1, keepdim=True)


def test_quaternion_products_compose_rotations():
    generator = torch.Generator().manual_seed(0)
    a, b = _random_quats(50, generator), _random_quats(50, generator)
    product = geometry.quat_to_matrix(geometry.quat_multiply(a, b))
    assert torch.allclose(product, geometry.quat_to_matrix(a) @ geometry.quat_to_matrix(b), atol=1e-12)
    inverse = geometry.quat_to_matrix(geometry.quat_conjugate(a))
    assert torch.allclose(inverse, geometry.quat_to_matrix(a).transpose(-1, -2), atol=1e-12)
    vectors = torch.randn(50, 3, generator=generator, dtype=torch.float64)
    rotated = geometry.quat_rotate(a, vectors)
    assert torch.allclose(rotated, (geometry.quat_to_matrix(a) @ vectors[..., None])[..., 0], atol=1e-12)
    assert torch.allclose(geometry.quat_rotate(a, rotated, inverse=True), vectors, atol=1e-12)


def test_matrix_to_quaternion_round_trip_with_a_non_negative_w():
    generator = torch.Generator().manual_seed(1)
    quats = _random_quats(200, generator)
    back = geometry.quat_from_matrix(geometry.quat_to_matrix(quats))
    assert bool((back[:, 0] >= 0).all())
    assert torch.allclose(back, quats * torch.sign(quats[:, :1]), atol=1e-12)
    # every pivot of Shepperd's method: rotations by pi about each axis and the identity
    for quat in ([0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0], [1.0, 0.0, 0.0, 0.0]):
        q = torch.tensor([quat], dtype=torch.float64)
        assert torch.allclose(geometry.quat_from_matrix(geometry.quat_to_matrix(q)), q, atol=1e-12)


def test_numpy_arrays_get_the_same_numbers_back_as_numpy():
    generator = torch.Generator().manual_seed(2)
    quats = _random_quats(20, generator).reshape(4, 5, 4)
    for function, argument in ((geometry.quat_to_matrix, quats), (geometry.quat_conjugate, quats),
                               (geometry.quat_from_matrix, geometry.quat_to_matrix(quats))):
        from_numpy = function(argument.numpy())
        assert isinstance(from_numpy, np.ndarray) and from_numpy.dtype == np.float64
        assert np.array_equal(from_numpy, function(argument).numpy())
    product = geometry.quat_multiply(quats.numpy(), quats.flip(0).numpy())
    assert np.array_equal(product, geometry.quat_multiply(quats, quats.flip(0)).numpy())


def test_quaternions_from_free_vectors():
    assert torch.equal(geometry.quat_from_vector(torch.zeros(2, 3)), torch.tensor([[1.0, 0, 0, 0], [1.0, 0, 0, 0]]))
    angle = 1.2
    q = geometry.quat_from_vector(torch.tensor([0.0, 0.0, math.tan(angle / 2)]))
    assert torch.allclose(q, torch.tensor([math.cos(angle / 2), 0.0, 0.0, math.sin(angle / 2)]), atol=1e-6)


def test_sh_basis_is_orthonormal_on_the_sphere():
    generator = torch.Generator().manual_seed(3)
    directions = torch.randn(200000, 3, generator=generator, dtype=torch.float64)
    basis = geometry.sh_basis(3, directions)
    gram = basis.T @ basis * (4 * math.pi / directions.shape[0])  # Monte Carlo integral over the sphere
    assert torch.allclose(gram, torch.eye(16, dtype=torch.float64), atol=0.03)
    assert torch.allclose(basis[:, 0], torch.full_like(basis[:, 0], geometry.SH_C0))


def test_camera_centre_and_pose_matching():
    rotation = geometry.quat_to_matrix(torch.tensor([0.9, 0.1, -0.3, 0.2]) / torch.tensor([0.9, 0.1, -0.3, 0.2]).norm())
    centre = torch.tensor([0.5, -2.0, 1.5])
    world_to_camera = torch.eye(4)
    world_to_camera[:3, :3] = rotation
    world_to_camera[:3, 3] = -rotation @ centre
    assert torch.allclose(geometry.camera_centre(world_to_camera), centre, atol=1e-6)
    generator = torch.Generator().manual_seed(4)
    poses = torch.randn(6, 3, 4, 4, generator=generator)
    grown = torch.cat([poses[4], torch.randn(2, 4, 4, generator=generator)])  # extra rows are ignored
    best, matched = geometry.match_pose(poses, grown)
    assert int(best) == 4 and float(matched) == 1.0
    best, matched = geometry.match_pose(poses, poses[2] + 1e-3)
    assert int(best) == 2 and float(matched) == 0.0


def test_fourier_features_and_mlp_builder():
    values = torch.tensor([[0.25, -0.5]])
    features = geometry.fourier_features(values, 2)
    expected = torch.cat([values, torch.sin(math.pi * values), torch.cos(math.pi * values),
                          torch.sin(2 * math.pi * values), torch.cos(2 * math.pi * values)], dim=-1)
    assert torch.allclose(features, expected)
    network = geometry.mlp(5, 8, 2, 3, activation=torch.nn.SiLU, layer_norm=True)
    kinds = [type(module).__name__ for module in network]
    assert kinds == ["Linear", "LayerNorm", "SiLU", "Linear", "LayerNorm", "SiLU", "Linear"]
    assert network(torch.randn(4, 5)).shape == (4, 3)
    assert [type(module).__name__ for module in geometry.mlp(5, 8, 1)] == ["Linear", "ReLU"]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_quaternion_functions_keep_the_dtype(dtype):
    generator = torch.Generator().manual_seed(5)
    quats = _random_quats(3, generator, dtype=dtype)
    assert geometry.quat_to_matrix(quats).dtype == dtype
    assert geometry.quat_from_matrix(geometry.quat_to_matrix(quats)).dtype == dtype


def test_rows_linear_matches_torch_linear_in_values_and_gradients(device):
    """The MLPs' Linear (bias gradient as a matrix-vector product) gives torch.nn.Linear's values and gradients
    on random rows, keeps its state dict, and passes finite differences in float64."""
    torch.manual_seed(3)
    ours = geometry.Linear(13, 7).to(device)
    reference = torch.nn.Linear(13, 7).to(device)
    reference.load_state_dict(ours.state_dict())
    x = torch.randn(301, 13, device=device, requires_grad=True)
    upstream = torch.randn(301, 7, device=device)
    for layer in (ours, reference):
        layer.zero_grad()
    x_ref = x.detach().clone().requires_grad_(True)
    (ours(x) * upstream).sum().backward()
    (reference(x_ref) * upstream).sum().backward()
    torch.testing.assert_close(ours(x), reference(x_ref))
    torch.testing.assert_close(x.grad, x_ref.grad)
    torch.testing.assert_close(ours.weight.grad, reference.weight.grad)
    torch.testing.assert_close(ours.bias.grad, reference.bias.grad)
    assert ours.state_dict().keys() == reference.state_dict().keys()
    double = geometry.Linear(5, 3).to(device).double()
    rows = torch.randn(11, 5, device=device, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a, w, b: geometry._RowsLinear.apply(a, w, b),
                                    (rows, double.weight, double.bias))
