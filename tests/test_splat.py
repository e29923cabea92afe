"""Tests of the Warp Gaussian rasterizer (``warpavatar.ops.rasterize_gaussians``) against the plain-torch reference.

Scenes are small (up to 300 Gaussians, 64x48 pixels) and mix the awkward cases: Gaussians partly off-screen,
behind the camera or on the near plane, very anisotropic, sub-pixel, and piles that saturate pixels.
"""

import contextlib
import itertools
import math

import pytest
import torch
import warp as wp

from warpavatar import ops
from warpavatar._src import splat as splat_bridge
from warpavatar._src.warp_utils import to_warp, torch_stream_scope
from warpavatar._torch_impl import splat as reference
from warpavatar.kernels import splat as kernels

DIFFERENTIABLE = ("means", "quats", "scales", "opacities", "colors", "background")


def _random_rotation(generator: torch.Generator) -> torch.Tensor:
    q, r = torch.linalg.qr(torch.randn(3, 3, generator=generator, dtype=torch.float64))
    q = q * torch.sign(torch.diagonal(r))
    if torch.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def make_scene(seed: int, *, gaussian_count: int = 200, width: int = 56, height: int = 44, sh_degree=None,
               device="cpu", with_background: bool = True, opacity_range=(0.05, 0.95), awkward: bool = True):
    """A random scene as a dict of float32 tensors plus sizes; camera with a random pose and off-centre K.

    With ``awkward``, 1/8 of the Gaussians each are placed around and beyond the image border, behind the camera
    or on the near plane, made very anisotropic, made sub-pixel; 1/16 are opaque and centred on pixels.
    """
    generator = torch.Generator().manual_seed(seed)

    def uniform(low, high, *shape):
        return low + (high - low) * torch.rand(*shape, generator=generator, dtype=torch.float64)

    fx, fy = 0.9 * width, 0.85 * width
    cx, cy = (width - 1) / 2 + 2.3, (height - 1) / 2 - 1.7
    # Camera-space centres: a visible bulk, then off-screen, behind-camera and near-plane groups.
    depth = uniform(1.5, 5.0, gaussian_count)
    spread = torch.stack([depth * width / (2 * fx), depth * height / (2 * fy)], dim=-1)
    xy = uniform(-1.0, 1.0, gaussian_count, 2) * spread
    group = gaussian_count // 8 if awkward else 0
    xy[:group] *= uniform(1.0, 1.5, group, 1)  # around and beyond the image border
    depth[group: group + group // 2] = uniform(-2.0, 0.0, group // 2)  # behind the camera
    depth[group + group // 2: 2 * group] = uniform(0.0, 0.02, group - group // 2)  # near plane
    # Pinned: centred on a pixel with opacity 1, so alpha hits the 0.999 clamp there.
    pinned = slice(4 * group, 4 * group + group // 2)
    pinned_count = group // 2
    columns = torch.randint(0, width, (pinned_count,), generator=generator)
    rows = torch.randint(0, height, (pinned_count,), generator=generator)
    xy[pinned, 0] = (columns - cx) * depth[pinned] / fx
    xy[pinned, 1] = (rows - cy) * depth[pinned] / fy
    points_camera = torch.cat([xy, depth[:, None]], dim=-1)

    rotation = _random_rotation(generator)
    translation = uniform(-0.5, 0.5, 3)
    world_to_camera = torch.eye(4, dtype=torch.float64)
    world_to_camera[:3, :3], world_to_camera[:3, 3] = rotation, translation
    means = (points_camera - translation) @ rotation  # R^T (p - t)

    scales = torch.exp(uniform(math.log(0.01), math.log(0.25), gaussian_count, 3))
    scales[2 * group: 3 * group] *= torch.tensor([20.0, 0.05, 0.1], dtype=torch.float64)  # very anisotropic
    scales[3 * group: 4 * group] = uniform(1e-4, 1e-3, group, 3)  # sub-pixel
    quats = torch.randn(gaussian_count, 4, generator=generator, dtype=torch.float64)
    opacities = uniform(*opacity_range, gaussian_count)
    opacities[pinned] = 1.0
    if sh_degree is None:
        colors = uniform(0.0, 1.0, gaussian_count, 3)
    else:
        colors = 0.4 * torch.randn(gaussian_count, 16, 3, generator=generator, dtype=torch.float64)
    K = torch.tensor([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=torch.float64)
    scene = dict(means=means, quats=quats, scales=scales, opacities=opacities, colors=colors, K=K,
                 world_to_camera=world_to_camera)
    if with_background:
        scene["background"] = uniform(0.0, 1.0, 3)
    scene = {name: value.to(device=device, dtype=torch.float32) for name, value in scene.items()}
    return scene, dict(width=width, height=height, sh_degree=sh_degree)


def render(rasterize, scene, sizes, *, densify_grad_out=None, return_info=False):
    return rasterize(
        scene["means"], scene["quats"], scene["scales"], scene["opacities"], scene["colors"], scene["K"],
        scene["world_to_camera"], sizes["width"], sizes["height"], background=scene.get("background"),
        sh_degree=sizes["sh_degree"], densify_grad_out=densify_grad_out, return_info=return_info,
    )


def render_and_grad(rasterize, scene, sizes, cotangents, *, densify=False, dtype=torch.float32):
    """Outputs, gradients of every differentiable input present, and the densification statistic.

    ``dtype=torch.float64`` runs the (reference) rasterizer on float64 copies of the scene; results are
    returned as float32.
    """
    scene = {name: value.detach().to(dtype).requires_grad_(name in DIFFERENTIABLE) for name, value in scene.items()}
    densify_out = torch.zeros(scene["means"].shape[0], 2, device=scene["means"].device) if densify else None
    outputs = render(rasterize, scene, sizes, densify_grad_out=densify_out)
    names = [name for name in DIFFERENTIABLE if name in scene]
    grads = torch.autograd.grad(outputs, [scene[name] for name in names], [c.to(dtype) for c in cotangents])
    outputs = tuple(output.detach().float() for output in outputs)
    return outputs, {name: grad.float() for name, grad in zip(names, grads)}, densify_out


def render_reference(scene, sizes, cotangents, *, densify=False):
    """The float64 plain-torch reference: the ground truth the float32 Warp op is held to."""
    return render_and_grad(reference.rasterize_gaussians, scene, sizes, cotangents, densify=densify,
                           dtype=torch.float64)


def random_cotangents(sizes, device, seed):
    generator = torch.Generator().manual_seed(1000 + seed)
    shapes = [(sizes["height"], sizes["width"], 3), (sizes["height"], sizes["width"]), (sizes["height"], sizes["width"])]
    return [torch.randn(*shape, generator=generator).to(device) for shape in shapes]


def assert_images_close(actual, expected, name):
    # A pixel where float32 rounding flips an alpha threshold changes by about 1/255 of a colour (or depth);
    # allow a handful of those, nothing more.
    scale = max(expected.abs().max().item(), 1.0)
    difference = (actual - expected).abs() / scale
    assert difference.max().item() < 5e-3, f"{name}: max relative difference {difference.max().item():.3g}"
    assert difference.mean().item() < 3e-5, f"{name}: mean relative difference {difference.mean().item():.3g}"


def assert_grads_close(actual, expected, name, rtol=3e-3):
    scale = expected.abs().max().item()
    error = (actual - expected).abs().max().item()
    assert scale > 0, f"{name}: reference gradient is zero, the test would prove nothing"
    assert error <= rtol * scale + 1e-6, f"{name}: max gradient error {error:.3g} vs scale {scale:.3g}"


@contextlib.contextmanager
def cpu_cooperative_blocks():
    """Run CPU launches with 256-thread blocks (CPU fibers), the CUDA execution model, for this block only."""
    previous = wp.config.enable_cpu_blocks
    wp.config.enable_cpu_blocks = True
    try:
        yield
    finally:
        wp.config.enable_cpu_blocks = previous


# ------------------------------------------------------------------------------------------------------------


def test_the_references_cover_every_op_with_the_same_signature():
    import inspect

    from warpavatar import _torch_impl

    # rasterizer_status reads the info dict of either rasterizer, rasterizer_replays sets how ours runs: neither
    # is an op of its own
    op_names = [name for name in ops.__all__ if name not in ("rasterizer_status", "rasterizer_replays")]
    assert sorted(_torch_impl.__all__) == sorted(op_names)
    for name in op_names:
        ours, theirs = inspect.signature(getattr(ops, name)), inspect.signature(getattr(_torch_impl, name))
        assert [(p.name, p.kind, p.default) for p in ours.parameters.values()] == \
            [(p.name, p.kind, p.default) for p in theirs.parameters.values()], name


@pytest.mark.parametrize(
    "seed, sh_degree, width, height, gaussian_count",
    [(0, None, 56, 44, 200), (1, 0, 40, 32, 120), (2, 1, 64, 48, 300), (3, 2, 48, 40, 160), (4, 3, 56, 44, 250)],
)
def test_matches_reference(device, seed, sh_degree, width, height, gaussian_count):
    scene, sizes = make_scene(seed, gaussian_count=gaussian_count, width=width, height=height, sh_degree=sh_degree,
                              device=device, with_background=seed % 2 == 0)
    cotangents = random_cotangents(sizes, device, seed)
    outputs, grads, densify = render_and_grad(ops.rasterize_gaussians, scene, sizes, cotangents, densify=True)
    ref_outputs, ref_grads, ref_densify = render_reference(scene, sizes, cotangents, densify=True)
    for actual, expected, name in zip(outputs, ref_outputs, ("image", "alpha", "depth")):
        assert actual.shape == expected.shape and actual.dtype == torch.float32
        assert_images_close(actual, expected, name)
    assert ref_outputs[1].max() > 0.5, "the scene should cover part of the image"
    for name in ref_grads:
        assert_grads_close(grads[name], ref_grads[name], name)
    assert_grads_close(densify, ref_densify, "densify_grad_out")


def test_info_matches_reference(device):
    scene, sizes = make_scene(5, device=device)
    *_, info = render(ops.rasterize_gaussians, scene, sizes, return_info=True)
    *_, ref_info = render(reference.rasterize_gaussians, scene, sizes, return_info=True)
    assert info["radii"].dtype == torch.int32 and info["radii"].shape == (200, 2)
    assert torch.equal(info["radii"], ref_info["radii"])
    kept = ref_info["radii"].any(dim=1)
    assert 0 < kept.sum() < 200, "the scene should have both culled and kept Gaussians"
    torch.testing.assert_close(info["means2d"][kept], ref_info["means2d"][kept], atol=1e-3, rtol=1e-5)
    assert torch.all(info["means2d"][~kept] == 0)
    torch.testing.assert_close(info["depths"], ref_info["depths"].float(), atol=1e-5, rtol=1e-5)
    assert set(info) == set(ref_info) and len(info) == len(ref_info) == 4
    assert info["means2d"] is info["means2d"], "made once, when first read"
    with pytest.raises(KeyError):
        info["conics"]


def test_saturated_piles_need_several_batches(device):
    # 700 opaque, large Gaussians over a 40x32 image: tiles list more than 256 of them (several shared batches)
    # and most pixels stop early on the transmittance floor.
    scene, sizes = make_scene(6, gaussian_count=700, width=40, height=32, device=device, opacity_range=(0.3, 0.99),
                              awkward=False)
    scene["scales"] = scene["scales"].clamp(min=0.12)
    means2d, conics, _, radii = reference.project_gaussians(scene["means"], scene["quats"], scene["scales"],
                                                            scene["K"], scene["world_to_camera"], 40, 32,
                                                            opacities=scene["opacities"])
    reached = reference.reached_tiles(means2d, conics, scene["opacities"], radii, 40, 32)
    assert reached.sum(dim=0).max() > 256
    cotangents = random_cotangents(sizes, device, 6)
    outputs, grads, _ = render_and_grad(ops.rasterize_gaussians, scene, sizes, cotangents)
    ref_outputs, ref_grads, _ = render_reference(scene, sizes, cotangents)
    assert (ref_outputs[1] > 0.999).float().mean() > 0.5, "most pixels should saturate"
    for actual, expected, name in zip(outputs, ref_outputs, ("image", "alpha", "depth")):
        assert_images_close(actual, expected, name)
    for name in ref_grads:
        assert_grads_close(grads[name], ref_grads[name], name)


@pytest.mark.parametrize("kernel", ["default", "wide"])
def test_both_backward_kernels_match_reference(device, kernel, monkeypatch):
    """The compositing backward's two kernels (launch bounds and warp sums of their own), each forced on every
    grid: a pile of several batches per tile, then a scene with the densification sums (12 values a Gaussian)."""
    chosen = kernels.composite_backward_kernel if kernel == "default" else kernels.composite_backward_wide_kernel
    monkeypatch.setattr(kernels, "backward_kernel_for", lambda tile_count, device: chosen)
    pile, pile_sizes = make_scene(6, gaussian_count=700, width=40, height=32, device=device,
                                  opacity_range=(0.3, 0.99), awkward=False)
    pile["scales"] = pile["scales"].clamp(min=0.12)
    for seed, (scene, sizes) in ((6, (pile, pile_sizes)), (2, make_scene(2, gaussian_count=300, width=64, height=48,
                                                                          sh_degree=1, device=device))):
        cotangents = random_cotangents(sizes, device, seed)
        with cpu_cooperative_blocks():
            _, grads, densify = render_and_grad(ops.rasterize_gaussians, scene, sizes, cotangents, densify=True)
        _, ref_grads, ref_densify = render_reference(scene, sizes, cotangents, densify=True)
        for name in ref_grads:
            assert_grads_close(grads[name], ref_grads[name], f"{kernel} {name}")
        assert_grads_close(densify, ref_densify, f"{kernel} densify_grad_out")


def test_backward_kernel_choice_follows_the_grid(device):
    chosen = kernels.backward_kernel_for
    if not wp.get_device(device).is_cuda:
        assert chosen(10**6, device) is kernels.composite_backward_kernel
        return
    sms = wp.get_device(device).sm_count
    assert chosen(kernels.WIDE_GRID_TILES_PER_SM * sms - 1, device) is kernels.composite_backward_kernel
    assert chosen(kernels.WIDE_GRID_TILES_PER_SM * sms, device) is kernels.composite_backward_wide_kernel


def test_cpu_cooperative_blocks_match_reference():
    """The CUDA execution model on CPU: 256 fibers per tile sharing batches, block-wide early exit."""
    for seed, count, sh_degree in ((7, 700, None), (8, 200, 3)):
        scene, sizes = make_scene(seed, gaussian_count=count, width=40, height=32, sh_degree=sh_degree,
                                  awkward=count != 700)
        if count == 700:
            scene["scales"] = scene["scales"].clamp(min=0.12)
        cotangents = random_cotangents(sizes, "cpu", seed)
        with cpu_cooperative_blocks():
            outputs, grads, densify = render_and_grad(ops.rasterize_gaussians, scene, sizes, cotangents, densify=True)
        ref_outputs, ref_grads, ref_densify = render_reference(scene, sizes, cotangents, densify=True)
        for actual, expected, name in zip(outputs, ref_outputs, ("image", "alpha", "depth")):
            assert_images_close(actual, expected, name)
        for name in ref_grads:
            assert_grads_close(grads[name], ref_grads[name], name)
        assert_grads_close(densify, ref_densify, "densify_grad_out")


def test_pixel_centre_convention(device):
    # A small round Gaussian whose mean projects (with the given K) to column 9, row 6 peaks on that pixel,
    # with equal neighbours left/right and up/down.
    width, height = 20, 14
    K = torch.tensor([[30.0, 0.0, 9.5], [0.0, 30.0, 6.5], [0.0, 0.0, 1.0]], device=device)
    z = 2.0
    mean = torch.tensor([[(9 - 9.5) * z / 30.0, (6 - 6.5) * z / 30.0, z]], device=device)
    image, alpha, depth = ops.rasterize_gaussians(
        mean, torch.tensor([[1.0, 0.0, 0.0, 0.0]], device=device), torch.full((1, 3), 0.05, device=device),
        torch.tensor([0.9], device=device), torch.ones(1, 3, device=device), K, torch.eye(4, device=device),
        width, height)
    row, column = divmod(int(alpha.argmax()), width)
    assert (column, row) == (9, 6)
    torch.testing.assert_close(alpha[6, 8], alpha[6, 10], rtol=1e-4, atol=1e-6)
    torch.testing.assert_close(alpha[5, 9], alpha[7, 9], rtol=1e-4, atol=1e-6)
    torch.testing.assert_close(depth[6, 9], alpha[6, 9] * z, rtol=1e-5, atol=1e-6)


def smooth_scene(device, *, width=14, height=12):
    """Five wide, half-transparent Gaussians that cover the whole tiny image with alpha well above 1/255.

    No pixel sits near a threshold (alpha floor, transmittance floor, 0.999 clamp), so the image is a smooth
    function of the inputs and finite differences are meaningful.
    """
    scene, sizes = make_scene(9, gaussian_count=5, width=width, height=height, sh_degree=1, device=device)
    scene["means"] = torch.tensor(
        [[0.0, 0.0, 0.0], [0.08, -0.05, 0.2], [-0.1, 0.04, 0.35], [0.03, 0.09, -0.25], [-0.05, -0.08, 0.1]],
        device=device)
    scene["world_to_camera"] = torch.eye(4, device=device)
    scene["world_to_camera"][2, 3] = 2.5
    scene["scales"] = torch.tensor([[1.0, 0.6, 0.8], [0.9, 1.1, 0.7], [0.7, 0.8, 1.2], [1.2, 0.9, 0.6],
                                    [0.8, 0.8, 0.8]], device=device)
    scene["scales"] *= 1.5
    scene["opacities"] = torch.tensor([0.3, 0.45, 0.25, 0.5, 0.35], device=device)
    scene["colors"] = scene["colors"][:, :4]
    scene["K"][0, 2], scene["K"][1, 2] = (width - 1) / 2, (height - 1) / 2
    # Check the claim: every Gaussian has alpha within (2/255, 0.999) at every pixel.
    means2d, conics, _, radii = reference.project_gaussians(scene["means"], scene["quats"], scene["scales"],
                                                            scene["K"], scene["world_to_camera"], width, height,
                                                            opacities=scene["opacities"])
    assert torch.all(radii > 0)
    rows, columns = torch.meshgrid(torch.arange(height, device=device) + 0.5, torch.arange(width, device=device) + 0.5,
                                   indexing="ij")
    dx, dy = means2d[:, 0, None, None] - columns, means2d[:, 1, None, None] - rows
    sigma = 0.5 * (conics[:, 0, None, None] * dx**2 + conics[:, 2, None, None] * dy**2) + conics[:, 1, None, None] * dx * dy
    alpha = scene["opacities"][:, None, None] * torch.exp(-sigma)
    assert alpha.min() > 2 / 255 and alpha.max() < 0.999
    return scene, sizes


def test_gradients_of_float64_reference_match_finite_differences():
    scene, sizes = smooth_scene("cpu")
    names = list(DIFFERENTIABLE)
    inputs = [scene[name].double().requires_grad_() for name in names]

    def function(*values):
        local = dict(scene, **dict(zip(names, values)))
        return render(reference.rasterize_gaussians, local, sizes)

    assert torch.autograd.gradcheck(function, inputs, eps=1e-6, atol=1e-5, rtol=1e-4, fast_mode=True)


def test_gradients_match_finite_differences(device):
    """Directional central differences of the Warp op itself (float32, so loose), for every input."""
    scene, sizes = smooth_scene(device)
    cotangents = random_cotangents(sizes, device, 10)

    def loss(values):
        outputs = render(ops.rasterize_gaussians, values, sizes)
        return sum((output.double() * weight.double()).sum() for output, weight in zip(outputs, cotangents))

    _, grads, _ = render_and_grad(ops.rasterize_gaussians, scene, sizes, cotangents)
    generator = torch.Generator().manual_seed(11)
    for name in DIFFERENTIABLE:
        direction = torch.randn(scene[name].shape, generator=generator).to(device)
        step = 2e-3
        plus = loss(dict(scene, **{name: scene[name] + step * direction}))
        minus = loss(dict(scene, **{name: scene[name] - step * direction}))
        numeric = ((plus - minus) / (2 * step)).item()
        analytic = (grads[name].double() * direction.double()).sum().item()
        assert abs(analytic) > 1e-2, f"{name}: the directional derivative should not vanish"
        assert abs(numeric - analytic) <= 1e-2 * abs(analytic) + 1e-2, f"{name}: {numeric} vs {analytic}"


def test_densify_grad_out_accumulates(device):
    scene, sizes = make_scene(12, gaussian_count=80, width=40, height=32, device=device)
    cotangents = random_cotangents(sizes, device, 12)
    _, _, once = render_and_grad(ops.rasterize_gaussians, scene, sizes, cotangents, densify=True)
    accumulated = torch.zeros_like(once)
    for _ in range(2):
        params = {name: value.detach().clone().requires_grad_(name == "means") for name, value in scene.items()}
        outputs = render(ops.rasterize_gaussians, params, sizes, densify_grad_out=accumulated)
        torch.autograd.backward(outputs, cotangents)
    assert once.abs().max() > 0
    torch.testing.assert_close(accumulated, 2 * once, rtol=1e-5, atol=1e-6)


def test_empty_and_fully_culled_scenes(device):
    scene, sizes = make_scene(13, gaussian_count=16, width=24, height=20, device=device)
    background = scene["background"]
    for count, shift in ((0, 0.0), (16, -10.0)):  # no Gaussians; all of them behind the camera
        local = {name: value[:count] if name in ("means", "quats", "scales", "opacities", "colors") else value
                 for name, value in scene.items()}
        local["means"] = local["means"] + shift * scene["world_to_camera"][2, :3]
        cotangents = random_cotangents(sizes, device, 13)
        outputs, grads, densify = render_and_grad(ops.rasterize_gaussians, local, sizes, cotangents, densify=True)
        image, alpha, depth = outputs
        torch.testing.assert_close(image, background.expand(sizes["height"], sizes["width"], 3))
        assert torch.all(alpha == 0) and torch.all(depth == 0)
        for name in ("means", "quats", "scales", "opacities", "colors"):
            assert grads[name].shape == local[name].shape and torch.all(grads[name] == 0)
        torch.testing.assert_close(grads["background"], cotangents[0].sum(dim=(0, 1)))
        assert torch.all(densify == 0)


def test_capacity_buffers_without_pairs_or_with_fewer_gaussians_than_tiles(device):
    # The tile ranges are cleared by the key emission (its threads stride over the tiles: 6 Gaussians, 80 tiles
    # here), or by a fill when there is no pair to emit; the image must be the reference's either way.
    scene, sizes = make_scene(25, gaussian_count=6, width=160, height=128, device=device, awkward=False)
    kernel_tile_pairs(scene, dict(sizes, sh_degree=None))  # the emission clears all 80 ranges (kernel_emit checks)
    names = ("means", "quats", "scales", "opacities", "colors")
    for count, shift, capacity in ((0, 0.0, 64), (6, -10.0, 64), (6, 0.0, None), (6, 0.0, 500), (6, 0.0, 7)):
        local = {name: value[:count] if name in names else value for name, value in scene.items()}
        local["means"] = local["means"] + shift * scene["world_to_camera"][2, :3]
        garbage = torch.full((4 * 80 * 2,), -3, dtype=torch.int32, device=device)  # for the allocator to hand out
        del garbage
        args = [local[name] for name in names + ("K", "world_to_camera")]
        image, alpha, depth, info = ops.rasterize_gaussians(*args, sizes["width"], sizes["height"],
                                                            background=local["background"], return_info=True,
                                                            intersection_capacity=capacity)
        pair_count = int(info["status"][0])
        assert (pair_count > 7) == (count > 0 and shift == 0.0), pair_count
        expected = render(reference.rasterize_gaussians, {k: v.double() for k, v in local.items()},
                          dict(sizes, sh_degree=None))
        if capacity is None or capacity >= pair_count:
            for actual, wanted, name in zip((image, alpha, depth), expected, ("image", "alpha", "depth")):
                assert_images_close(actual, wanted.float(), name)
        else:  # pairs dropped: only the shallowest pairs composited, still a finite image over the background
            assert torch.isfinite(image).all() and 0 < int((alpha > 0).sum()) < int((expected[1] > 0).sum())


def test_rejects_bad_inputs(device):
    scene, sizes = make_scene(14, gaussian_count=8, width=16, height=16, device=device)

    def call(**changes):
        local = dict(scene)
        local.update({name: value for name, value in changes.items() if name in scene})
        kwargs = {name: value for name, value in changes.items() if name not in scene}
        args = dict(width=16, height=16, background=local["background"], sh_degree=None)
        args.update(kwargs)
        return ops.rasterize_gaussians(local["means"], local["quats"], local["scales"], local["opacities"],
                                       local["colors"], local["K"], local["world_to_camera"], **args)

    call()  # the unchanged scene is fine
    with pytest.raises(ValueError, match="means"):
        call(means=scene["means"][:, :2])
    with pytest.raises(ValueError, match="quats"):
        call(quats=scene["quats"][:5])
    with pytest.raises(ValueError, match="scales"):
        call(scales=scene["scales"][:, None])
    with pytest.raises(ValueError, match="opacities"):
        call(opacities=scene["opacities"][:, None])
    with pytest.raises(ValueError, match="colors"):
        call(colors=scene["colors"][:, :2])
    with pytest.raises(ValueError, match="K"):
        call(K=scene["K"][:2])
    with pytest.raises(ValueError, match="world_to_camera"):
        call(world_to_camera=scene["world_to_camera"][:3])
    with pytest.raises(ValueError, match="background"):
        call(background=scene["background"][:2])
    with pytest.raises(TypeError, match="means"):
        call(means=scene["means"].long())
    with pytest.raises(TypeError, match="width"):
        call(width=16.0)
    with pytest.raises(ValueError, match="height"):
        call(height=0)
    with pytest.raises(ValueError, match="sh_degree"):
        call(sh_degree=4, colors=torch.zeros(8, 25, 3, device=device))
    with pytest.raises(ValueError, match="coefficients"):
        call(sh_degree=2, colors=torch.zeros(8, 4, 3, device=device))
    with pytest.raises(ValueError, match="densify_grad_out"):
        call(densify_grad_out=torch.zeros(8, 3, device=device))
    with pytest.raises(TypeError, match="densify_grad_out"):
        call(densify_grad_out=torch.zeros(8, 2, device=device, dtype=torch.float64))
    for name in ("means", "quats", "scales", "opacities", "colors"):
        corrupted = scene[name].clone()
        corrupted.view(-1)[3] = float("nan") if name != "scales" else float("inf")
        with pytest.raises(ValueError, match=f"non-finite values in {name}"):
            call(**{name: corrupted})
    corrupted_K = scene["K"].clone()
    corrupted_K[0, 0] = float("inf")
    with pytest.raises(ValueError, match="non-finite values in K"):
        call(K=corrupted_K)


def test_matches_gsplat_when_available(device):
    """Same image as gsplat 1.5.3 (K shifted by half a pixel for its convention); skipped without gsplat/CUDA."""
    if not device.startswith("cuda"):
        pytest.skip("gsplat's rasterizer runs on CUDA only")
    gsplat = pytest.importorskip("gsplat")
    scene, sizes = make_scene(15, gaussian_count=300, width=64, height=48, sh_degree=3, device=device)
    image, alpha, _ = render(ops.rasterize_gaussians, scene, sizes)
    K_gsplat = scene["K"].clone()
    K_gsplat[0, 2] += 0.5
    K_gsplat[1, 2] += 0.5
    colors, alphas, _ = gsplat.rasterization(
        scene["means"], scene["quats"], scene["scales"], scene["opacities"], scene["colors"],
        scene["world_to_camera"][None], K_gsplat[None], sizes["width"], sizes["height"], sh_degree=3)
    # composite over the background here: gsplat's own background argument expects other shapes across versions
    expected = colors[0] + (1.0 - alphas[0]) * scene["background"]
    assert_images_close(image, expected, "image vs gsplat")
    assert_images_close(alpha, alphas[0, ..., 0], "alpha vs gsplat")


# ------------------------------------------------------------------------------------------------------------
# The opacity-aware extent and the exact tile test


def kernel_projection(scene, sizes):
    """Run the Warp projection kernel on the scene's device: a dict of its outputs (``depth_keys`` [2 N] and
    ``records`` [2 N, 2] are the depth sort's double buffers, the first halves written) and ``counts`` (the
    tile counts, in Gaussian order)."""
    n, device = scene["means"].shape[0], scene["means"].device
    f32, i32 = dict(dtype=torch.float32, device=device), dict(dtype=torch.int32, device=device)
    out = dict(xy_opacity=torch.empty(n, 3, **f32), conics=torch.empty(n, 3, **f32),
               color_depth=torch.empty(n, 4, **f32), radii=torch.empty(n, 2, **i32),
               depth_keys=torch.empty(2 * n, **f32), records=torch.empty(2 * n, 2, **i32))
    flags = torch.zeros(1, **i32)
    degree = -1 if sizes["sh_degree"] is None else sizes["sh_degree"]
    colors = scene["colors"].reshape(n, -1, 3).contiguous()
    with torch_stream_scope(device):
        kernels.launch_project(
            to_warp(scene["means"], wp.vec3), to_warp(scene["quats"], wp.vec4), to_warp(scene["scales"], wp.vec3),
            to_warp(scene["opacities"]), to_warp(colors, wp.vec3), to_warp(scene["K"].reshape(1, 3, 3), wp.mat33),
            to_warp(scene["world_to_camera"].reshape(1, 4, 4), wp.mat44), width=sizes["width"],
            height=sizes["height"], sh_degree=degree, used_coefficients=1 if degree < 0 else (degree + 1) ** 2,
            xy_opacity=to_warp(out["xy_opacity"], wp.vec3), conics=to_warp(out["conics"], wp.vec3),
            color_depth=to_warp(out["color_depth"], wp.vec4), radii=to_warp(out["radii"], wp.vec2i),
            depth_keys=to_warp(out["depth_keys"][:n]), depth_order=to_warp(out["records"][:n], wp.vec2i),
            bad_input_flags=to_warp(flags))
    out["counts"] = out["records"][:n, 1].clone()
    return out


def kernel_depth_sort(projection):
    """The op's depth sort of the projection's records (in place) and the prefix sum of their counts: the
    depth-ordered records [N, 2] and ``tile_ends`` [N]."""
    n = projection["counts"].shape[0]
    keys, records = projection["depth_keys"], projection["records"]
    ends = torch.empty(n, dtype=torch.int32, device=keys.device)
    with torch_stream_scope(keys.device):
        wp.utils.radix_sort_pairs(to_warp(keys), to_warp(records, wp.vec2i), n, begin_bit=0,
                                  end_bit=kernels.DEPTH_SORT_BITS)
        wp.utils.array_scan(to_warp(records[:n, 1]), to_warp(ends), inclusive=True)
    return records[:n], ends


def kernel_emit(projection, records, ends, sizes, keys, ids, threads_per_gaussian=None):
    """The key emission over ``records`` (the Gaussians in some order, with their counts) into ``keys``/``ids``;
    asserts that it cleared a tile-ranges buffer full of garbage."""
    tile_count = math.ceil(sizes["width"] / 16) * math.ceil(sizes["height"] / 16)
    ranges = torch.full((tile_count, 2), -5, dtype=torch.int32, device=keys.device)
    with torch_stream_scope(keys.device):
        kernels.launch_emit_tile_keys(to_warp(projection["xy_opacity"], wp.vec3),
                                      to_warp(projection["conics"], wp.vec3), to_warp(projection["radii"], wp.vec2i),
                                      to_warp(records, wp.vec2i), to_warp(ends), width=sizes["width"],
                                      height=sizes["height"], keys=to_warp(keys), gaussian_ids=to_warp(ids),
                                      tile_ranges=to_warp(ranges), threads_per_gaussian=threads_per_gaussian)
    assert torch.all(ranges == 0)


def kernel_tile_pairs(scene, sizes):
    """The (Gaussian, tile) pairs the Warp kernels emit, as a [N, tiles] bool mask; their count; radii.

    Runs the projection and the key emission in Gaussian order (the records as the projection wrote them, the
    prefix sum of the counts); asserts that no padding key was needed (the emission accepted as many tiles as
    the projection counted), that each Gaussian's slots hold its tiles in increasing id and no pair repeats.
    """
    tiles_x, tiles_y = math.ceil(sizes["width"] / 16), math.ceil(sizes["height"] / 16)
    n, device = scene["means"].shape[0], scene["means"].device
    projection = kernel_projection(scene, sizes)
    counts = projection["counts"]
    assert torch.equal(projection["records"][:n, 0].cpu(), torch.arange(n, dtype=torch.int32))
    pair_count = int(counts.sum())
    keys, ids = (torch.empty(pair_count, dtype=torch.int32, device=device) for _ in range(2))
    kernel_emit(projection, projection["records"][:n], torch.cumsum(counts, 0).to(torch.int32), sizes, keys, ids)
    keys, ids = keys.cpu().long(), ids.cpu().long()
    assert torch.all(keys < tiles_x * tiles_y), "the emission padded: it accepted fewer tiles than counted"
    assert torch.equal(ids, torch.repeat_interleave(torch.arange(n), counts.cpu().long()))
    assert torch.all((ids[1:] != ids[:-1]) | (keys[1:] > keys[:-1])), "a Gaussian's tiles in increasing id"
    mask = torch.zeros(n, tiles_x * tiles_y, dtype=torch.bool)
    mask[ids, keys] = True
    assert int(mask.sum()) == pair_count, "a (Gaussian, tile) pair was emitted twice"
    return mask, pair_count, projection["radii"].cpu()


def contributing_tiles(scene, sizes):
    """[N, tiles] bool, brute force in float64: tiles holding a pixel where the Gaussian's alpha >= 1/255.

    Every Gaussian in the depth range is tested at every pixel, with no box and no culling by opacity.
    """
    width, height = sizes["width"], sizes["height"]
    s = {name: value.double() for name, value in scene.items()}
    means2d, conics, depths, _ = reference.project_gaussians(s["means"], s["quats"], s["scales"], s["K"],
                                                             s["world_to_camera"], width, height,
                                                             opacities=torch.ones_like(s["opacities"]))
    rows, columns = torch.meshgrid(torch.arange(height) + 0.5, torch.arange(width) + 0.5, indexing="ij")
    dx = means2d[:, 0, None] - columns.reshape(1, -1).double()
    dy = means2d[:, 1, None] - rows.reshape(1, -1).double()
    sigma = 0.5 * (conics[:, 0:1] * dx**2 + conics[:, 2:3] * dy**2) + conics[:, 1:2] * dx * dy
    alpha = torch.clamp_max(s["opacities"][:, None] * torch.exp(-sigma), reference.ALPHA_MAX)
    in_range = ((depths > reference.NEAR_PLANE) & (depths < reference.FAR_PLANE))[:, None]
    contributes = in_range & (sigma >= 0) & (alpha >= reference.ALPHA_THRESHOLD)  # [N, pixels]
    tiles_x = math.ceil(width / 16)
    tile_of_pixel = ((rows.long() // 16) * tiles_x + columns.long() // 16).reshape(-1)
    mask = torch.zeros(contributes.shape[0], tiles_x * math.ceil(height / 16), dtype=torch.bool)
    index = tile_of_pixel.expand_as(contributes)
    return mask.scatter_reduce(1, index, contributes, reduce="amax")


def render_without_tiles(scene, sizes):
    """The float64 reference with every kept Gaussian listed in every tile (the all-pairs render)."""
    original = reference.reached_tiles

    def every_tile(means2d, conics, opacities, radii, width, height):
        kept = (radii > 0).any(dim=1, keepdim=True)
        return kept.expand(-1, math.ceil(width / 16) * math.ceil(height / 16))

    reference.reached_tiles = every_tile
    try:
        return render(reference.rasterize_gaussians, {k: v.double() for k, v in scene.items()}, sizes)
    finally:
        reference.reached_tiles = original


def near_threshold_scene(seed, *, width=72, height=56, count=300):
    """``make_scene``'s awkward scene with the Gaussians around the border and those after the pinned ones made
    12x longer and thinner (not the anisotropic group, already needles) up to ~70 %, and opacities straddling
    1/255 (0.8/255 to 2/255) from ~2/3 on."""
    scene, sizes = make_scene(seed, gaussian_count=count, width=width, height=height)
    generator = torch.Generator().manual_seed(seed)
    group = count // 8
    elongation = torch.tensor([12.0, 0.08, 0.3])
    scene["scales"][:group] *= elongation
    scene["scales"][4 * group + group // 2: 7 * count // 10] *= elongation
    faint = slice(2 * count // 3, count)
    scene["opacities"][faint] = (0.8 + 1.2 * torch.rand(count - 2 * count // 3, generator=generator)) / 255
    return scene, sizes


@pytest.mark.parametrize("seed", [20, 21])
def test_extent_and_tile_test_never_drop_a_contributing_pixel(seed):
    scene, sizes = near_threshold_scene(seed)
    needed = contributing_tiles(scene, sizes)
    emitted, pair_count, radii = kernel_tile_pairs(scene, sizes)
    assert needed.sum() > 500 and (needed.sum(dim=1) > 4).sum() > 20, "the scene should span many tiles"
    assert not torch.any(needed & ~emitted), "the kernels dropped a (Gaussian, tile) pair with alpha >= 1/255"
    faint = scene["opacities"] < 1 / 255
    assert faint.sum() > 10 and torch.all(radii[faint] == 0), "Gaussians below 1/255 opacity are culled"
    # The float64 reference lists the same pairs up to float32 rounding at the ellipse's edge, also covers
    # every needed one, and its image equals the all-pairs render exactly.
    s64 = {name: value.double() for name, value in scene.items()}
    means2d, conics, _, ref_radii = reference.project_gaussians(
        s64["means"], s64["quats"], s64["scales"], s64["K"], s64["world_to_camera"], sizes["width"],
        sizes["height"], opacities=s64["opacities"])
    listed = reference.reached_tiles(means2d, conics, s64["opacities"], ref_radii, sizes["width"], sizes["height"])
    assert not torch.any(needed & ~listed)
    assert (listed ^ emitted).sum() <= 0.01 * pair_count
    with_tiles = render(reference.rasterize_gaussians, s64, sizes)
    for listed_output, all_pairs_output in zip(with_tiles, render_without_tiles(scene, sizes)):
        assert torch.equal(listed_output, all_pairs_output)
    for actual, expected, name in zip(render(ops.rasterize_gaussians, scene, sizes), with_tiles,
                                      ("image", "alpha", "depth")):
        assert_images_close(actual, expected.float(), name)


def test_tile_test_lists_fewer_pairs_on_elongated_gaussians():
    scene, sizes = make_scene(22, gaussian_count=150, width=128, height=96, awkward=False)
    scene["scales"] *= torch.tensor([10.0, 0.1, 0.1])  # needles in random orientations
    emitted, pair_count, radii = kernel_tile_pairs(scene, sizes)
    s64 = {name: value.double() for name, value in scene.items()}
    means2d = render(reference.rasterize_gaussians, s64, sizes, return_info=True)[3]["means2d"].double() + 0.5
    boxes = reference._tile_boxes(means2d, radii, 8, 6)
    box_count = int(((boxes[:, 1] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 2]))[(radii > 0).any(dim=1)].sum())
    assert pair_count < 0.6 * box_count, f"{pair_count} pairs listed against {box_count} in the boxes"
    for listed_output, all_pairs_output in zip(render(reference.rasterize_gaussians, s64, sizes),
                                               render_without_tiles(scene, sizes)):
        assert torch.equal(listed_output, all_pairs_output)
    for actual, expected, name in zip(render(ops.rasterize_gaussians, scene, sizes), render_without_tiles(scene, sizes),
                                      ("image", "alpha", "depth")):
        assert_images_close(actual, expected.float(), name)


def scene_with_depth_ties(device):
    """``make_scene``'s awkward scene with two groups of Gaussians sharing one centre each (so one depth, to
    the bit), of different shapes: the binning must order them by index."""
    scene, sizes = make_scene(24, gaussian_count=200, device=device)
    for first, last in ((150, 156), (170, 174)):
        scene["means"][first + 1: last] = scene["means"][first]
    return scene, sizes


def test_tile_ranges_match_reference_and_skip_padding(device):
    # A hand-made list of a 3-tile grid: tile 0 twice, tile 2 three times, then two padding keys (tile id 3).
    keys = torch.tensor([0, 0, 2, 2, 2, 3, 3], dtype=torch.int32, device=device)
    for launch in (kernels.launch_tile_ranges, kernels.launch_tile_ranges_padded):
        ranges = torch.zeros(3, 2, dtype=torch.int32, device=device)
        with torch_stream_scope(device):
            launch(to_warp(keys), keys.shape[0], to_warp(ranges))
        assert ranges.tolist() == [[0, 2], [0, 0], [2, 5]]
    # Random sorted lists over 40 tiles, some absent, with and without padding, against the reference.
    generator = torch.Generator().manual_seed(31)
    present = torch.randperm(40, generator=generator)[:25]
    for padding in (0, 17):
        tiles = torch.sort(present[torch.randint(0, 25, (300,), generator=generator)]).values
        keys = torch.cat([tiles, torch.full((padding,), 40)]).to(device=device, dtype=torch.int32)
        expected = reference.tile_ranges(keys.cpu(), 40)
        assert (expected[:, 1] > expected[:, 0]).sum() >= 20 and (expected[:, 1] == 0).sum() >= 10
        for launch in (kernels.launch_tile_ranges, kernels.launch_tile_ranges_padded):
            ranges = torch.zeros(40, 2, dtype=torch.int32, device=device)
            with torch_stream_scope(device):
                launch(to_warp(keys), keys.shape[0], to_warp(ranges))
            assert torch.equal(ranges.cpu(), expected)


def test_depth_sort_and_emission_match_reference(device):
    scene, sizes = scene_with_depth_ties(device)
    n = scene["means"].shape[0]
    mask, pair_count, _ = kernel_tile_pairs(scene, sizes)  # the pairs, emitted in Gaussian order
    projection = kernel_projection(scene, sizes)
    depths = projection["color_depth"][:, 3].cpu()
    counts = projection["counts"].cpu()
    assert torch.equal(counts, mask.sum(dim=1).to(torch.int32))
    # The projection's depth-sort inputs.
    expected_keys, expected_records = reference.depth_sort_keys(depths, counts)
    assert torch.equal(projection["depth_keys"][:n].cpu(), expected_keys)
    assert torch.equal(projection["records"][:n].cpu(), expected_records)
    s64 = {name: value.double().cpu() for name, value in scene.items()}
    _, _, ref_depths, _ = reference.project_gaussians(s64["means"], s64["quats"], s64["scales"], s64["K"],
                                                      s64["world_to_camera"], sizes["width"], sizes["height"],
                                                      opacities=s64["opacities"])
    torch.testing.assert_close(depths, ref_depths.float(), atol=1e-5, rtol=1e-5)
    # The depth sort: stable, ties in index order; the prefix sum of the counts in that order.
    order = torch.argsort(expected_keys, stable=True)
    kept = counts > 0
    for first, last in ((150, 156), (170, 174)):
        assert kept[first:last].sum() >= 2 and len(set(depths[first:last].tolist())) == 1
    records, ends = kernel_depth_sort(projection)
    assert torch.equal(records[:, 0].cpu().long(), order)
    assert torch.equal(ends.cpu(), torch.cumsum(counts[order], 0).to(torch.int32))
    # The emission in depth order: exact, dropping pairs past a small capacity, padding a large one; with the
    # device's threads per Gaussian and with one, three and eight (runs of slots that split rows).
    assert mask.sum(dim=1).max() > 8, "some Gaussian should have more pairs than threads"
    for capacity, threads in itertools.product((None, 2 * pair_count // 3, pair_count + 37), (None, 1, 3, 8)):
        size = pair_count if capacity is None else capacity
        keys, ids = (torch.full((size + 5,), -7, dtype=torch.int32, device=device) for _ in range(2))
        kernel_emit(projection, records, ends, sizes, keys[:size], ids[:size], threads_per_gaussian=threads)
        expected_tiles, expected_ids = reference.emit_tile_keys(mask, order, capacity=capacity)
        assert torch.equal(keys[:size].cpu(), expected_tiles) and torch.equal(ids[:size].cpu(), expected_ids)
        assert torch.all(keys[size:] == -7) and torch.all(ids[size:] == -7), "written past the buffer"
    with pytest.raises(ValueError, match="threads_per_gaussian must be >= 1, got 0"):
        kernel_emit(projection, records, ends, sizes, keys[:size], ids[:size], threads_per_gaussian=0)


@pytest.mark.parametrize("mode", ["exact", "padded capacity", "small capacity"])
def test_sorted_pairs_are_ordered_by_tile_depth_and_index(device, mode, monkeypatch):
    monkeypatch.setattr(splat_bridge, "_RECENT_PAIRS", {})  # "exact": no recent call to speculate from (on CUDA)
    scene, sizes = scene_with_depth_ties(device)
    mask, pair_count, _ = kernel_tile_pairs(scene, sizes)
    capacity = {"exact": None, "padded capacity": pair_count + 53, "small capacity": 2 * pair_count // 3}[mode]
    scene = {name: value.requires_grad_(name in DIFFERENTIABLE) for name, value in scene.items()}
    args = [scene[name] for name in ("means", "quats", "scales", "opacities", "colors", "K", "world_to_camera")]
    image, _, _, info = ops.rasterize_gaussians(*args, sizes["width"], sizes["height"], background=scene["background"],
                                                return_info=True, intersection_capacity=capacity)
    assert int(info["status"][0]) == pair_count
    saved = image.grad_fn.saved_pass
    tile_ranges, sorted_ids = saved.tile_ranges.cpu(), saved.sorted_ids.cpu()
    tile_count = tile_ranges.shape[0]
    tiles = torch.full(sorted_ids.shape, tile_count, dtype=torch.int32)  # slots in no range: padding
    for tile, (start, end) in enumerate(tile_ranges.tolist()):
        tiles[start:end] = tile
    expected_tiles, expected_ids = reference.sorted_pairs(mask, info["depths"].cpu(), capacity=capacity)
    assert torch.equal(tiles, expected_tiles)
    assert torch.equal(sorted_ids, expected_ids)
    assert torch.equal(tile_ranges, reference.tile_ranges(expected_tiles, tile_count))
    # Ties: neighbours in one tile at one depth, which only the index orders.
    real = expected_ids >= 0
    pair_depths = info["depths"].cpu()[expected_ids[real].long()]
    same = (expected_tiles[real][1:] == expected_tiles[real][:-1]) & (pair_depths[1:] == pair_depths[:-1])
    assert same.sum() >= (2 if mode == "small capacity" else 4)  # the small capacity keeps fewer of them
    if mode == "padded capacity":
        assert torch.all(sorted_ids[pair_count:] == -1)
        exact = ops.rasterize_gaussians(*args, sizes["width"], sizes["height"], background=scene["background"])[0]
        assert torch.equal(image, exact)


def test_backward_keeps_one_sorted_id_per_pair_and_no_per_gaussian_scratch(device, monkeypatch):
    # What the forward saves for the backward: one sorted Gaussian id per (Gaussian, tile) pair (the sort's
    # double buffer is released), and per-Gaussian records of 48 bytes; the gradients come out of one
    # allocation sized without the |d mean2d| sums when no densification statistic is asked for. (The exact
    # mode: with no recent calls to guess from; the speculative mode's buffers are in test_splat_speculative.)
    monkeypatch.setattr(splat_bridge, "_RECENT_PAIRS", {})
    scene, sizes = make_scene(5, device=device, gaussian_count=160)
    scene = {name: value.requires_grad_(name in DIFFERENTIABLE) for name, value in scene.items()}
    image, alpha, depth, info = render(ops.rasterize_gaussians, scene, sizes, return_info=True)
    pair_count = int(info["status"][0])
    assert pair_count > 100
    saved = image.grad_fn.saved_pass
    sorted_ids = saved.sorted_ids
    assert sorted_ids.dtype == torch.int32 and sorted_ids.shape == (pair_count,)
    assert sorted_ids.untyped_storage().nbytes() == 4 * pair_count
    n = scene["means"].shape[0]
    # The four per-Gaussian records share one allocation of 48 bytes a Gaussian (radii 8, projected means and
    # opacities 12, conics 12, colours and depths 16), laid end to end.
    records = (saved.radii, saved.xy_opacity, saved.conics, saved.color_depth)
    storage = saved.radii.untyped_storage()
    assert all(t.untyped_storage().data_ptr() == storage.data_ptr() and t.is_contiguous() for t in records)
    assert storage.nbytes() == 48 * n
    assert sorted(t.data_ptr() - storage.data_ptr() for t in records) == [0, 8 * n, 20 * n, 32 * n]
    grads = torch.autograd.grad((image, alpha, depth), [scene["means"], scene["opacities"]],
                                random_cotangents(sizes, device, 5))
    # means' and opacities' gradients share the one zeroed buffer: 10 screen-space floats, 13 parameter floats.
    assert grads[0].untyped_storage().data_ptr() == grads[1].untyped_storage().data_ptr()
    assert grads[0].untyped_storage().nbytes() == (10 + 13) * 4 * n
    assert grads[0].abs().sum() > 0 and grads[1].abs().sum() > 0


def test_a_pass_without_gradients_keeps_its_sorted_ids_in_place(device, monkeypatch):
    # No backward will read a pass whose inputs need no gradient: its sorted ids stay a view of the sort's
    # double buffer (no copy), its per-pixel state (final transmittance, last index) is not written, and its
    # outputs are those of a pass that keeps the compact copy and the state.
    monkeypatch.setattr(splat_bridge, "_RECENT_PAIRS", {})
    scene, sizes = make_scene(5, device=device, gaussian_count=160)
    inputs = [scene[name] for name in ("means", "quats", "scales", "opacities")]
    inputs.append(scene["colors"].reshape(160, 1, 3))  # RGB as one coefficient (sh_degree -1), as the bridge passes it
    background = torch.zeros(3, device=device)
    args = (*inputs, background, scene["K"], scene["world_to_camera"])
    kept, count = splat_bridge.run_pass(*args, width=sizes["width"], height=sizes["height"], sh_degree=-1,
                                        capacity=None, speculative=False, compact_ids=True,
                                        buffers=splat_bridge.allocate_pass_buffers(160, sizes["width"],
                                                                                   sizes["height"], device))
    untouched = splat_bridge.allocate_pass_buffers(160, sizes["width"], sizes["height"], device)
    untouched.final_transmittance.fill_(-7.0)
    untouched.last_index.fill_(-7)
    in_place, same_count = splat_bridge.run_pass(*args, width=sizes["width"], height=sizes["height"], sh_degree=-1,
                                                 capacity=None, speculative=False, compact_ids=False,
                                                 pixel_state=False, buffers=untouched)
    assert count == same_count > 100
    assert kept.sorted_ids.untyped_storage().nbytes() == 4 * count
    assert in_place.sorted_ids.untyped_storage().nbytes() == 8 * count
    assert torch.equal(kept.sorted_ids, in_place.sorted_ids)
    for name in ("image", "alpha", "depth"):
        assert torch.equal(getattr(kept, name), getattr(in_place, name))
    assert (in_place.final_transmittance == -7.0).all() and (in_place.last_index == -7).all()
    assert torch.allclose(kept.final_transmittance, 1.0 - kept.alpha, atol=1e-6) and (kept.last_index >= 0).any()
