"""Tests of the skinning ops (sample_grid, lbs, inverse_lbs): Warp kernels against the plain-torch references,
finite differences, geometric identities, edge cases and input validation, on every available device."""

import math

import pytest
import torch

from warpavatar import ops
from warpavatar._src import skinning as skinning_src
from warpavatar._torch_impl import skinning as reference
from warpavatar.geometry import quat_to_matrix

SEEDS = (0, 1, 2)


# ---------------------------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------------------------


def assert_close_relative(actual, expected, tolerance, what=""):
    """max |actual - expected| <= tolerance * max |expected| (compares in float64)."""
    assert actual.shape == expected.shape, f"{what}: shape {tuple(actual.shape)} != {tuple(expected.shape)}"
    actual = actual.detach().double().cpu()
    expected = expected.detach().double().cpu()
    scale = max(expected.abs().max().item(), 1e-6) if expected.numel() else 1.0
    error = (actual - expected).abs().max().item() if expected.numel() else 0.0
    assert error <= tolerance * scale, f"{what}: max error {error:.3e} > {tolerance:.1e} * {scale:.3e}"


def generator_for(seed, device="cpu"):
    return torch.Generator(device="cpu").manual_seed(seed)


def random_rotations(count, generator, *, max_angle=1.0):
    """[count, 3, 3] float64 rotations about random axes by angles in [0, max_angle) radians (Rodrigues)."""
    axis = torch.randn(count, 3, generator=generator, dtype=torch.float64)
    axis = axis / axis.norm(dim=1, keepdim=True)
    angle = torch.rand(count, 1, 1, generator=generator, dtype=torch.float64) * max_angle
    cross = torch.zeros(count, 3, 3, dtype=torch.float64)
    cross[:, 0, 1], cross[:, 0, 2], cross[:, 1, 2] = -axis[:, 2], axis[:, 1], -axis[:, 0]
    cross = cross - cross.transpose(1, 2)
    return torch.eye(3, dtype=torch.float64) + angle.sin() * cross + (1.0 - angle.cos()) * cross @ cross


def random_bones(bone_count, generator, *, noise=0.15, max_angle=1.0):
    """[J, 4, 4] float32 affine bones: rotation times (I + noise), random translation, bottom row 0 0 0 1."""
    bones = torch.eye(4, dtype=torch.float64).repeat(bone_count, 1, 1)
    stretch = torch.eye(3, dtype=torch.float64) + noise * torch.randn(bone_count, 3, 3, generator=generator,
                                                                     dtype=torch.float64)
    bones[:, :3, :3] = random_rotations(bone_count, generator, max_angle=max_angle) @ stretch
    bones[:, :3, 3] = 0.5 * torch.randn(bone_count, 3, generator=generator, dtype=torch.float64)
    return bones.float()


def random_weights(point_count, bone_count, generator):
    weights = torch.rand(point_count, bone_count, generator=generator) + 0.05
    return weights / weights.sum(dim=1, keepdim=True)


def random_quats(point_count, generator):
    quats = torch.randn(point_count, 4, generator=generator)
    return quats / quats.norm(dim=1, keepdim=True)



def directional_check(function, inputs, index, cotangents, *, eps, tolerance, generator):
    """Compare autograd's gradient of <cotangents, function(inputs)> along a random direction of
    inputs[index] with a central difference of the float32 op."""
    inputs = [x.detach().clone() for x in inputs]
    inputs[index].requires_grad_(True)
    outputs = function(*inputs)
    (grad,) = torch.autograd.grad(outputs, inputs[index], cotangents)
    direction = torch.randn(inputs[index].shape, generator=generator).to(inputs[index].device)

    def objective(step):
        shifted = [x.detach().clone() for x in inputs]
        shifted[index] = shifted[index] + step * direction
        values = function(*shifted)
        return sum((v.double() * c.double()).sum() for v, c in zip(values, cotangents)).item()

    numeric = (objective(eps) - objective(-eps)) / (2 * eps)
    analytic = (grad.double() * direction.double()).sum().item()
    assert abs(numeric - analytic) <= tolerance * max(abs(numeric), abs(analytic), 1e-3), (
        f"input {index}: finite difference {numeric:.6g} != autograd {analytic:.6g}"
    )


# ---------------------------------------------------------------------------------------------------------
# sample_grid
# ---------------------------------------------------------------------------------------------------------

BOX_MIN = (-0.5, -1.0, 0.0)
BOX_MAX = (0.5, 1.0, 2.0)


def random_points_around_box(point_count, generator, *, margin=0.2):
    """Points in the box widened by ``margin`` of its size on each side (some are clamped)."""
    low, high = torch.tensor(BOX_MIN), torch.tensor(BOX_MAX)
    unit = torch.rand(point_count, 3, generator=generator) * (1 + 2 * margin) - margin
    return low + unit * (high - low)


@pytest.fixture(params=["point", "channel"])
def sampler_layout(request, monkeypatch):
    """Run a test with each thread layout of the sampler kernels, whatever the device's default."""
    for device_type in ("cpu", "cuda"):
        monkeypatch.setitem(skinning_src._SAMPLE_GRID_LAYOUT, device_type, request.param)
    return request.param


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("shape", [(4, 5, 6, 3), (3, 2, 4, 24), (5, 3, 4, 41), (1, 4, 3, 2)])
def test_sample_grid_matches_grid_sample(device, sampler_layout, seed, shape):
    generator = generator_for(seed)
    grid = torch.randn(shape, generator=generator).to(device)
    points = random_points_around_box(200, generator).to(device)
    grid.requires_grad_(True)
    points.requires_grad_(True)
    values = ops.sample_grid(grid, points, BOX_MIN, BOX_MAX)
    grid64 = grid.detach().double().requires_grad_(True)
    points64 = points.detach().double().requires_grad_(True)
    expected = reference.sample_grid(grid64, points64, BOX_MIN, BOX_MAX)
    assert values.dtype == torch.float32 and values.device == grid.device
    assert_close_relative(values, expected, 1e-5, "values")
    cotangent = torch.randn(values.shape, generator=generator).to(device)
    grad_grid, grad_points = torch.autograd.grad(values, (grid, points), cotangent)
    expected_grid, expected_points = torch.autograd.grad(expected, (grid64, points64), cotangent.double())
    assert_close_relative(grad_grid, expected_grid, 1e-5, "grad grid")
    assert_close_relative(grad_points, expected_points, 1e-4, "grad points")


def test_sample_grid_axis_order_and_samples(device, sampler_layout):
    """At a sample's position the value is that sample: x runs along W, y along H, z along D."""
    depth, height, width = 3, 4, 5
    grid = torch.randn(depth, height, width, 2).to(device)
    d, h, w = torch.meshgrid(torch.arange(depth), torch.arange(height), torch.arange(width), indexing="ij")
    low, high = torch.tensor(BOX_MIN), torch.tensor(BOX_MAX)
    unit = torch.stack([w / (width - 1), h / (height - 1), d / (depth - 1)], dim=-1).reshape(-1, 3)
    points = (low + unit * (high - low)).to(device)
    values = ops.sample_grid(grid, points, BOX_MIN, BOX_MAX)
    torch.testing.assert_close(values, grid.reshape(-1, 2), atol=1e-5, rtol=0)
    # a midpoint along x only averages neighbours along W
    midpoint = (low + torch.tensor([0.5 / (width - 1), 0.0, 0.0]) * (high - low)).to(device)
    value = ops.sample_grid(grid, midpoint[None], BOX_MIN, BOX_MAX)
    torch.testing.assert_close(value[0], 0.5 * (grid[0, 0, 0] + grid[0, 0, 1]), atol=1e-5, rtol=0)


def test_sample_grid_border_gradient_convention(device, sampler_layout):
    """Outside the box values clamp to the border; the point gradient along an axis is 0 on or beyond its
    faces (torch grid_sampler's convention) and matches grid_sample everywhere."""
    generator = generator_for(3)
    grid = torch.randn(4, 5, 6, 3, generator=generator).to(device)
    low, high = torch.tensor(BOX_MIN), torch.tensor(BOX_MAX)
    inside = low + torch.tensor([0.37, 0.61, 0.43]) * (high - low)
    cases = []
    for axis in range(3):
        for coordinate in (low[axis] - 0.3, low[axis], high[axis], high[axis] + 0.7):
            point = inside.clone()
            point[axis] = coordinate
            cases.append(point)
    points = torch.stack(cases).to(device).requires_grad_(True)
    values = ops.sample_grid(grid, points, BOX_MIN, BOX_MAX)
    expected = reference.sample_grid(grid.double(), points.detach().double(), BOX_MIN, BOX_MAX)
    assert_close_relative(values, expected, 1e-5, "values")
    # clamped points take the border's value
    torch.testing.assert_close(values[0], values[1], atol=1e-6, rtol=0)
    torch.testing.assert_close(values[2], values[3], atol=1e-6, rtol=0)
    (grad_points,) = torch.autograd.grad(values, points, torch.ones_like(values))
    points64 = points.detach().double().requires_grad_(True)
    (expected_grad,) = torch.autograd.grad(
        reference.sample_grid(grid.double(), points64, BOX_MIN, BOX_MAX), points64, torch.ones_like(expected)
    )
    for case in range(len(cases)):
        axis = case // 4
        assert grad_points[case, axis].item() == 0.0
    assert_close_relative(grad_points, expected_grad, 1e-4, "grad points")
    assert grad_points.abs().sum() > 0  # the other axes still carry gradient


def test_sample_grid_finite_differences(device, sampler_layout):
    generator = generator_for(4)
    grid = torch.randn(3, 4, 3, 5, generator=generator).to(device)
    points = random_points_around_box(20, generator, margin=-0.05).to(device)
    cotangent = torch.randn(20, 5, generator=generator).to(device)

    def function(grid_, points_):
        return (ops.sample_grid(grid_, points_, BOX_MIN, BOX_MAX),)

    directional_check(function, [grid, points], 0, (cotangent,), eps=1e-2, tolerance=1e-3, generator=generator)
    # small steps so that no point leaves its cell
    directional_check(function, [grid, points], 1, (cotangent,), eps=1e-4, tolerance=2e-2, generator=generator)


def test_sample_grid_box_tensor_matches_sequence(device, sampler_layout):
    generator = generator_for(5)
    grid = torch.randn(3, 4, 5, 6, generator=generator).to(device).requires_grad_(True)
    points = random_points_around_box(50, generator).to(device)
    from_floats = ops.sample_grid(grid, points, BOX_MIN, BOX_MAX)
    from_tensors = ops.sample_grid(grid, points, torch.tensor(BOX_MIN, device=device),
                                   torch.tensor(BOX_MAX, device=device))
    torch.testing.assert_close(from_tensors, from_floats, atol=0, rtol=0)
    (grad_floats,) = torch.autograd.grad(from_floats.sum(), grid)
    (grad_tensors,) = torch.autograd.grad(from_tensors.sum(), grid)
    torch.testing.assert_close(grad_tensors, grad_floats, atol=1e-6, rtol=0)


@pytest.mark.parametrize("layout", ["point", "channel"])
def test_sample_grid_launchers_box_in_device_memory(device, layout):
    """The kernels read the box from device memory (the path CUDA tensors take) exactly as from arguments."""
    import warp as wp

    from warpavatar._src.warp_utils import to_warp, torch_stream_scope
    from warpavatar.kernels import skinning as kernels

    generator = generator_for(13)
    grid = torch.randn(3, 4, 5, 6, generator=generator).to(device)
    points = random_points_around_box(30, generator).to(device)
    grad_values = torch.randn(30, 6, generator=generator).to(device)
    box = torch.tensor([BOX_MIN, BOX_MAX], device=device)
    results = []
    for use_array in (False, True):
        values = torch.empty(30, 6, device=device)
        grad_grid = torch.zeros_like(grid)
        grad_points = torch.empty_like(points)
        box_options = dict(box=to_warp(box, dtype=wp.vec3)) if use_array else dict(box_low=BOX_MIN, box_high=BOX_MAX)
        with torch_stream_scope(device):
            kernels.sample_grid_forward(to_warp(grid), to_warp(points, dtype=wp.vec3), to_warp(values),
                                        layout=layout, **box_options)
            kernels.sample_grid_backward(to_warp(grid), to_warp(points, dtype=wp.vec3), to_warp(grad_values),
                                         grad_grid=to_warp(grad_grid), grad_points=to_warp(grad_points, dtype=wp.vec3),
                                         layout=layout, **box_options)
        results.append((values, grad_grid, grad_points))
    expected = reference.sample_grid(grid, points, BOX_MIN, BOX_MAX)
    assert_close_relative(results[0][0], expected, 1e-5, "values")
    for from_args, from_array in zip(*results):
        torch.testing.assert_close(from_array, from_args, atol=1e-6, rtol=0)
    with pytest.raises(ValueError, match="layout"):
        kernels.sample_grid_forward(to_warp(grid), to_warp(points, dtype=wp.vec3), to_warp(values), layout="voxel")
    with pytest.raises(ValueError, match="values must have shape"):
        kernels.sample_grid_forward(to_warp(grid), to_warp(points, dtype=wp.vec3), to_warp(values[:, :5]))


def test_sample_grid_only_one_input_requires_grad(device, sampler_layout):
    generator = generator_for(6)
    grid = torch.randn(3, 4, 5, 6, generator=generator).to(device)
    points = random_points_around_box(40, generator).to(device)
    cotangent = torch.randn(40, 6, generator=generator).to(device)
    both = torch.autograd.grad(
        ops.sample_grid(grid.requires_grad_(True), points.requires_grad_(True), BOX_MIN, BOX_MAX),
        (grid, points), cotangent,
    )
    (grid_only,) = torch.autograd.grad(
        ops.sample_grid(grid, points.detach(), BOX_MIN, BOX_MAX), grid, cotangent
    )
    (points_only,) = torch.autograd.grad(
        ops.sample_grid(grid.detach(), points, BOX_MIN, BOX_MAX), points, cotangent
    )
    torch.testing.assert_close(grid_only, both[0], atol=1e-6, rtol=0)
    torch.testing.assert_close(points_only, both[1], atol=1e-6, rtol=0)


def test_sample_grid_empty_inputs(device, sampler_layout):
    grid = torch.randn(3, 4, 5, 6).to(device).requires_grad_(True)
    points = torch.zeros(0, 3, device=device, requires_grad=True)
    values = ops.sample_grid(grid, points, BOX_MIN, BOX_MAX)
    assert values.shape == (0, 6)
    grad_grid, grad_points = torch.autograd.grad(values.sum(), (grid, points))
    assert grad_grid.shape == grid.shape and grad_grid.abs().sum() == 0
    assert grad_points.shape == (0, 3)
    no_channels = torch.zeros(3, 4, 5, 0, device=device, requires_grad=True)
    some_points = torch.rand(7, 3, device=device, requires_grad=True)
    values = ops.sample_grid(no_channels, some_points, BOX_MIN, BOX_MAX)
    assert values.shape == (7, 0)
    (grad_points,) = torch.autograd.grad(values.sum(), some_points)
    assert grad_points.shape == (7, 3) and grad_points.abs().sum() == 0


def test_sample_grid_non_finite_points(device):
    grid = torch.randn(3, 4, 5, 2).to(device)
    points = torch.tensor([[0.0, 0.0, 1.0], [math.nan, 0.0, 1.0], [math.inf, 0.0, 1.0]], device=device)
    values = ops.sample_grid(grid, points, BOX_MIN, BOX_MAX)
    assert torch.isfinite(values[0]).all()
    assert torch.isnan(values[1]).all()
    expected = ops.sample_grid(grid, torch.tensor([[BOX_MAX[0], 0.0, 1.0]], device=device), BOX_MIN, BOX_MAX)
    torch.testing.assert_close(values[2], expected[0])


def test_sample_grid_rejects_bad_inputs(device):
    grid = torch.randn(3, 4, 5, 2, device=device)
    points = torch.rand(6, 3, device=device)
    with pytest.raises(ValueError, match="grid must have shape"):
        ops.sample_grid(grid[0], points, BOX_MIN, BOX_MAX)
    with pytest.raises(ValueError, match="points must have shape"):
        ops.sample_grid(grid, points[:, :2], BOX_MIN, BOX_MAX)
    with pytest.raises(TypeError, match="float32"):
        ops.sample_grid(grid.double(), points, BOX_MIN, BOX_MAX)
    with pytest.raises(TypeError, match="float32"):
        ops.sample_grid(grid, points.double(), BOX_MIN, BOX_MAX)
    with pytest.raises(ValueError, match="at least one sample"):
        ops.sample_grid(torch.zeros(3, 0, 5, 2, device=device), points, BOX_MIN, BOX_MAX)
    with pytest.raises(ValueError, match="bbox_min must hold 3"):
        ops.sample_grid(grid, points, (0.0, 0.0), BOX_MAX)
    with pytest.raises(ValueError, match="bbox_max must have shape"):
        ops.sample_grid(grid, points, BOX_MIN, torch.ones(4, device=device))
    with pytest.raises(ValueError, match="exceed"):
        ops.sample_grid(grid, points, BOX_MIN, (0.5, -1.0, 2.0))
    with pytest.raises(ValueError, match="finite"):
        ops.sample_grid(grid, points, BOX_MIN, (0.5, math.inf, 2.0))
    with pytest.raises(TypeError, match="torch.Tensor"):
        ops.sample_grid(grid.tolist(), points, BOX_MIN, BOX_MAX)
    if device != "cpu":
        with pytest.raises(ValueError, match="cpu"):
            ops.sample_grid(grid, points.cpu(), BOX_MIN, BOX_MAX)


# ---------------------------------------------------------------------------------------------------------
# lbs and inverse_lbs
# ---------------------------------------------------------------------------------------------------------


def lbs_inputs(seed, point_count, bone_count, device):
    generator = generator_for(seed)
    points = torch.randn(point_count, 3, generator=generator)
    weights = random_weights(point_count, bone_count, generator)
    bones = random_bones(bone_count, generator)
    quats = random_quats(point_count, generator) * (0.5 + torch.rand(point_count, 1, generator=generator))
    return [x.to(device) for x in (points, weights, bones, quats)], generator


@pytest.mark.parametrize("inverse", [False, True], ids=["lbs", "inverse_lbs"])
@pytest.mark.parametrize("with_quats", [True, False], ids=["quats", "no_quats"])
@pytest.mark.parametrize("seed, bone_count", [(0, 1), (1, 3), (2, 24), (3, 41)])
def test_lbs_matches_reference(device, inverse, with_quats, seed, bone_count):
    (points, weights, bones, quats), generator = lbs_inputs(seed, 96, bone_count, device)
    op = ops.inverse_lbs if inverse else ops.lbs
    ref = reference.inverse_lbs if inverse else reference.lbs
    inputs = [points, weights, bones] + ([quats] if with_quats else [])
    inputs = [x.clone().requires_grad_(True) for x in inputs]
    inputs64 = [x.detach().double().requires_grad_(True) for x in inputs]
    out_points, out_quats = op(*inputs[:3], quats=inputs[3] if with_quats else None)
    ref_points, ref_quats = ref(*inputs64[:3], quats=inputs64[3] if with_quats else None)
    assert out_points.dtype == torch.float32 and out_points.device == points.device
    assert_close_relative(out_points, ref_points, 2e-5, "points")
    outputs, expected = [out_points], [ref_points]
    if with_quats:
        assert_close_relative(out_quats, ref_quats, 2e-5, "quats")
        outputs.append(out_quats)
        expected.append(ref_quats)
    else:
        assert out_quats is None and ref_quats is None
    cotangents = [torch.randn(x.shape, generator=generator).to(device) for x in outputs]
    grads = torch.autograd.grad(outputs, inputs, cotangents)
    expected_grads = torch.autograd.grad(expected, inputs64, [c.double() for c in cotangents])
    for name, grad, expected_grad in zip(("points", "weights", "bones", "quats"), grads, expected_grads):
        assert_close_relative(grad, expected_grad, 1e-4, f"grad {name}")
    assert grads[2][:, 3, :].abs().sum() == 0  # bottom rows are ignored


@pytest.mark.parametrize("seed", SEEDS)
def test_inverse_lbs_undoes_lbs(device, seed):
    (points, weights, bones, quats), _ = lbs_inputs(seed, 128, 24, device)
    posed, posed_quats = ops.lbs(points, weights, bones, quats=quats)
    back, back_quats = ops.inverse_lbs(posed, weights, bones, quats=posed_quats)
    assert_close_relative(back, points, 1e-5, "points")
    assert_close_relative(back_quats, quats, 1e-5, "quats")
    assert not torch.allclose(posed, points, atol=1e-2)


@pytest.mark.parametrize("seed", SEEDS)
def test_lbs_single_rigid_bone_is_rigid_transform(device, seed):
    """Weights all on one rigid bone: x' = R x + t, q' = q(R) q is unit and rotates vectors like R R(q)."""
    generator = generator_for(seed)
    bone_count, point_count = 5, 64
    bones = torch.eye(4, dtype=torch.float64).repeat(bone_count, 1, 1)
    bones[:, :3, :3] = random_rotations(bone_count, generator, max_angle=3.0)
    bones[:, :3, 3] = torch.randn(bone_count, 3, generator=generator, dtype=torch.float64)
    bones = bones.float()
    bone_of_point = torch.randint(0, bone_count, (point_count,), generator=generator)
    weights = torch.nn.functional.one_hot(bone_of_point, bone_count).float()
    points = torch.randn(point_count, 3, generator=generator)
    quats = random_quats(point_count, generator)
    posed, posed_quats = ops.lbs(points.to(device), weights.to(device), bones.to(device), quats=quats.to(device))
    rotation = bones[bone_of_point, :3, :3]
    expected = (rotation @ points[:, :, None]).squeeze(-1) + bones[bone_of_point, :3, 3]
    assert_close_relative(posed, expected, 1e-6, "points")
    torch.testing.assert_close(posed_quats.norm(dim=1).cpu(), torch.ones(point_count), atol=1e-6, rtol=0)
    vectors = torch.randn(point_count, 3, generator=generator)
    rotated = (quat_to_matrix(posed_quats.cpu()) @ vectors[:, :, None]).squeeze(-1)
    expected_rotated = (rotation @ quat_to_matrix(quats) @ vectors[:, :, None]).squeeze(-1)
    torch.testing.assert_close(rotated, expected_rotated, atol=1e-5, rtol=0)
    # the inverse maps the posed frame back
    back, back_quats = ops.inverse_lbs(posed, weights.to(device), bones.to(device), quats=posed_quats)
    assert_close_relative(back, points, 1e-5, "points back")
    assert_close_relative(back_quats, quats, 1e-5, "quats back")


@pytest.mark.parametrize("inverse", [False, True], ids=["lbs", "inverse_lbs"])
@pytest.mark.parametrize("case", ["affine", "rigid", "coaxial"])
def test_lbs_finite_differences(device, inverse, case):
    """Directional central differences of the float32 op, for every input. "rigid" bones make every singular
    value 1 and "coaxial" blends rotations about one axis (two equal singular values): the polar derivative
    must stay right where SVD-based derivatives break down."""
    generator = generator_for(7)
    point_count, bone_count = 5, 3
    if case == "affine":
        bones = random_bones(bone_count, generator)
    else:
        bones = torch.eye(4).repeat(bone_count, 1, 1)
        if case == "rigid":
            bones[:, :3, :3] = random_rotations(bone_count, generator).float()
        else:
            axis_angle = torch.rand(bone_count, generator=generator) * 1.5
            bones[:, 0, 0], bones[:, 0, 1] = axis_angle.cos(), -axis_angle.sin()
            bones[:, 1, 0], bones[:, 1, 1] = axis_angle.sin(), axis_angle.cos()
        bones[:, :3, 3] = torch.randn(bone_count, 3, generator=generator)
    if case == "rigid":
        weights = torch.nn.functional.one_hot(torch.arange(point_count) % bone_count, bone_count).float()
    else:
        weights = random_weights(point_count, bone_count, generator)
    points = torch.randn(point_count, 3, generator=generator)
    quats = random_quats(point_count, generator)
    inputs = [x.to(device) for x in (points, weights, bones, quats)]
    op = ops.inverse_lbs if inverse else ops.lbs

    def function(points_, weights_, bones_, quats_):
        return op(points_, weights_, bones_, quats=quats_)

    cotangents = [torch.randn(point_count, 3, generator=generator).to(device),
                  torch.randn(point_count, 4, generator=generator).to(device)]
    for index in range(4):
        directional_check(function, inputs, index, cotangents, eps=2e-3, tolerance=2e-3, generator=generator)


def test_closest_rotation_accuracy(device):
    """The rotation of hard matrices (random, det < 0 included) is accurate to float32 conditioning:
    Warp's svd3 alone can be off by 1e-2, the Newton polish must fix it."""
    generator = generator_for(8)
    count = 64
    linear = torch.randn(count, 3, 3, generator=generator, dtype=torch.float64)
    bones = torch.eye(4, dtype=torch.float64).repeat(count, 1, 1)
    bones[:, :3, :3] = linear
    identity = torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(count, 1)
    _, rotation = ops.lbs(torch.zeros(count, 3, device=device), torch.eye(count, device=device),
                          bones.float().to(device), quats=identity.to(device))
    expected = reference.closest_rotation_quat(bones.float().double()[:, :3, :3])
    assert (torch.linalg.det(linear) < 0).any()
    singular = torch.linalg.svdvals(linear)
    sign = torch.linalg.det(linear).sign()
    conditioning = singular[:, 0] / torch.minimum(singular[:, 1] + sign * singular[:, 2],
                                                  singular[:, 0] + sign * singular[:, 2])
    error = (rotation.cpu().double() - expected).abs().max(dim=1).values
    assert (error <= 1e-6 * conditioning.clamp_min(1.0)).all(), (error / conditioning).max()
    assert (rotation[:, 0] >= 0).all()


def test_lbs_empty_and_one_bone(device):
    weights = torch.zeros(0, 4, device=device, requires_grad=True)
    bones = torch.eye(4).repeat(4, 1, 1).to(device).requires_grad_(True)
    points = torch.zeros(0, 3, device=device, requires_grad=True)
    quats = torch.zeros(0, 4, device=device, requires_grad=True)
    for op in (ops.lbs, ops.inverse_lbs):
        out_points, out_quats = op(points, weights, bones, quats=quats)
        assert out_points.shape == (0, 3) and out_quats.shape == (0, 4)
        grads = torch.autograd.grad(out_points.sum() + out_quats.sum(), (points, weights, bones, quats))
        assert [tuple(g.shape) for g in grads] == [(0, 3), (0, 4), (4, 4, 4), (0, 4)]
        assert grads[2].abs().sum() == 0
        out_points, out_quats = op(points, weights, bones)
        assert out_points.shape == (0, 3) and out_quats is None
    # J = 1 with unit weights is the bone's transform itself
    (points, _, bones, quats), _ = lbs_inputs(9, 10, 1, device)
    posed, _ = ops.lbs(points, torch.ones(10, 1, device=device), bones)
    expected = points @ bones[0, :3, :3].T + bones[0, :3, 3]
    torch.testing.assert_close(posed, expected, atol=1e-5, rtol=0)


def test_lbs_weights_used_as_given(device):
    """Weights are not renormalized: doubling them doubles the blended transform."""
    (points, weights, bones, _), _ = lbs_inputs(10, 16, 4, device)
    posed, _ = ops.lbs(points, weights, bones)
    doubled, _ = ops.lbs(points, 2.0 * weights, bones)
    torch.testing.assert_close(doubled, 2.0 * posed, atol=1e-5, rtol=1e-5)


def test_lbs_non_contiguous_and_partial_grads(device):
    (points, weights, bones, quats), generator = lbs_inputs(11, 32, 6, device)
    strided_weights = weights.t().contiguous().t()  # same values, column-major strides
    assert not strided_weights.is_contiguous()
    torch.testing.assert_close(ops.lbs(points, strided_weights, bones, quats=quats)[1],
                               ops.lbs(points, weights, bones, quats=quats)[1])
    cotangents = (torch.randn(32, 3, generator=generator).to(device),
                  torch.randn(32, 4, generator=generator).to(device))
    full = torch.autograd.grad(
        ops.lbs(*(x.requires_grad_(True) for x in (points, weights, bones)), quats=quats.requires_grad_(True)),
        (points, weights, bones, quats), cotangents,
    )
    for index in range(4):
        inputs = [x.detach() for x in (points, weights, bones, quats)]
        inputs[index].requires_grad_(True)
        (alone,) = torch.autograd.grad(ops.lbs(*inputs[:3], quats=inputs[3]), inputs[index], cotangents)
        torch.testing.assert_close(alone, full[index], atol=1e-6, rtol=0)


def test_lbs_rejects_bad_inputs(device):
    (points, weights, bones, quats), _ = lbs_inputs(12, 8, 3, device)
    for op in (ops.lbs, ops.inverse_lbs):
        with pytest.raises(ValueError, match=r"bone_transforms must have shape \[\*, 4, 4\]"):
            op(points, weights, bones[:, :3, :])
        with pytest.raises(ValueError, match="weights has 7 rows"):
            op(points, weights[:7], bones)
        with pytest.raises(ValueError, match="3 columns but bone_transforms has 2 bones"):
            op(points, weights, bones[:2])
        with pytest.raises(ValueError, match="at least one bone"):
            op(points, weights[:, :0], bones[:0])
        with pytest.raises(ValueError, match="quats must have shape"):
            op(points, weights, bones, quats=quats[:, :3])
        with pytest.raises(ValueError, match="shape"):
            op(points[:, :2], weights, bones)
        with pytest.raises(TypeError, match="float32"):
            op(points.double(), weights, bones)
        with pytest.raises(TypeError, match="float32"):
            op(points, weights, bones, quats=quats.double())
        if device != "cpu":
            with pytest.raises(ValueError, match="cpu"):
                op(points, weights.cpu(), bones)
