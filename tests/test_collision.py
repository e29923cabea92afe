"""Tests of :func:`warpavatar.ops.push_out_of_capsules` against its plain-torch reference and finite differences.

Particles are scattered around several overlapping capsules (some inside one or two, some outside, some just
across a surface); values and gradients (random cotangents) are compared with the reference on every device,
and the Warp gradients with central differences of the float64 reference away from the map's kinks.
"""

import pytest
import torch

from conftest import assert_matches_central_differences
from warpavatar import ops
from warpavatar._torch_impl import collision as reference


def random_scene(seed, *, particle_count=400, capsule_count=6, device="cpu", dtype=torch.float32):
    """Overlapping capsules in a unit box and particles near them: inside, outside and close to a surface."""
    generator = torch.Generator().manual_seed(seed)
    start = torch.rand(capsule_count, 3, generator=generator, dtype=torch.float64) * 0.6
    end = start + (torch.rand(capsule_count, 3, generator=generator, dtype=torch.float64) - 0.5) * 0.8
    radius = 0.08 + 0.12 * torch.rand(capsule_count, generator=generator, dtype=torch.float64)
    # Each particle near a random capsule: a point of its segment (a little past its ends too) plus an offset
    # of 0.05 to 1.6 radii in a random direction.
    owner = torch.randint(0, capsule_count, (particle_count,), generator=generator)
    along = torch.rand(particle_count, 1, generator=generator, dtype=torch.float64) * 1.4 - 0.2
    direction = torch.randn(particle_count, 3, generator=generator, dtype=torch.float64)
    direction = direction / direction.norm(dim=1, keepdim=True)
    # (at least 5 % of a radius from the axis: closer, the normal of a float32 particle is ill-conditioned and a
    # GPU's fused multiply-adds round it differently; test_degenerate_cases_are_finite covers the axis itself)
    reach = (0.05 + 1.55 * torch.rand(particle_count, 1, generator=generator, dtype=torch.float64)) * radius[owner, None]
    x = start[owner] + along * (end - start)[owner] + reach * direction
    scene = {"x": x, "segment_start": start, "segment_end": end, "radius": radius}
    return {name: value.to(dtype=dtype, device=device) for name, value in scene.items()}


NAMES = ("x", "segment_start", "segment_end", "radius")


def leaves(scene, dtype=None):
    return {name: scene[name].detach().to(dtype or scene[name].dtype).clone().requires_grad_() for name in NAMES}


def call(op, scene):
    return op(*(scene[name] for name in NAMES))


def kink_margin(scene):
    """Per particle, the smallest distance (float64) to a kink of the map: a capsule surface or a segment end."""
    x, a, b, radius = (scene[name].double().cpu() for name in NAMES)
    d = b - a
    s = ((x[:, None] - a[None]) * d[None]).sum(-1) / (d * d).sum(-1)[None]
    closest = a[None] + s.clamp(0, 1)[..., None] * d[None]
    distance = (x[:, None] - closest).norm(dim=-1)
    surface = (distance - radius[None]).abs()
    ends = torch.minimum(s.abs(), (s - 1).abs()) * d.norm(dim=-1)[None]
    return torch.minimum(surface, ends).min(dim=1).values


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_matches_reference(device, seed):
    scene = random_scene(seed, device=device)
    ours, theirs = leaves(scene), leaves(scene)
    out, out_ref = call(ops.push_out_of_capsules, ours), call(reference.push_out_of_capsules, theirs)
    assert out.dtype == torch.float32 and out.device == out_ref.device
    # a few float32 ulps of the unit-size coordinates, times the normal's conditioning near the axis
    torch.testing.assert_close(out, out_ref, rtol=1e-5, atol=1e-5)
    moved = (out - scene["x"]).norm(dim=1) > 0
    # the scene exercises both branches, and particles held by two capsules at once
    assert 0.2 < moved.float().mean().item() < 0.9
    x, a, b, radius = (scene[name].double() for name in NAMES)
    d = b - a
    s = (((x[:, None] - a[None]) * d[None]).sum(-1) / (d * d).sum(-1)[None]).clamp(0, 1)
    inside = ((x[:, None] - a[None] - s[..., None] * d[None]).norm(dim=-1) < radius[None]).sum(1)
    assert (inside >= 2).sum() >= 10

    cotangent = torch.randn(out.shape, generator=torch.Generator().manual_seed(seed + 10)).to(device)
    grads = torch.autograd.grad(out, [ours[n] for n in NAMES], cotangent)
    grads_ref = torch.autograd.grad(out_ref, [theirs[n] for n in NAMES], cotangent)
    for name, grad, grad_ref in zip(NAMES, grads, grads_ref):
        assert grad.abs().max() > 0, name
        # the normal's derivative grows like 1 / (distance to the axis), up to 20 / radius here: float32 rounding
        # of the GPU's fused multiply-adds reaches 2e-5 on O(1) gradients (H100), far below a wrong term's O(1)
        torch.testing.assert_close(grad, grad_ref, rtol=1e-4, atol=1e-4, msg=lambda m, n=name: f"d/d{n}: {m}")


def test_single_capsule_puts_inside_particles_on_its_surface(device):
    scene = random_scene(3, capsule_count=1, particle_count=300, device=device)
    out = call(ops.push_out_of_capsules, scene)
    a, b, radius = scene["segment_start"][0], scene["segment_end"][0], scene["radius"][0]
    d = b - a

    def distance_to_segment(points):
        t = (((points - a) @ d) / (d @ d)).clamp(0, 1)
        return (points - a - t[:, None] * d).norm(dim=1)

    before, after = distance_to_segment(scene["x"]), distance_to_segment(out)
    inside = before < radius
    assert inside.sum() > 50 and (~inside).sum() > 50
    torch.testing.assert_close(after[inside], torch.full_like(after[inside], radius.item()), rtol=0, atol=2e-6)
    assert torch.equal(out[~inside], scene["x"][~inside])  # outside particles are untouched
    # A second pass changes nothing: every particle is now outside or on the surface.
    torch.testing.assert_close(call(ops.push_out_of_capsules, {**scene, "x": out}), out, rtol=0, atol=1e-6)


def test_finite_differences(device):
    # Warp float32 gradients against central differences of the float64 reference, away from kinks.
    scene = random_scene(4, particle_count=60, capsule_count=3, dtype=torch.float64)
    keep = kink_margin(scene) > 2e-3
    scene["x"] = scene["x"][keep]
    scene64 = {name: value.clone() for name, value in scene.items()}
    ours = leaves({name: value.to(device) for name, value in scene.items()}, dtype=torch.float32)
    out = call(ops.push_out_of_capsules, ours)
    cotangent = torch.randn(out.shape, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    grads = torch.autograd.grad(out, [ours[n] for n in NAMES], cotangent.float().to(device))

    def objective(values):
        return (call(reference.push_out_of_capsules, values) * cotangent).sum()

    assert_matches_central_differences(objective, scene64, dict(zip(NAMES, grads)), epsilon=1e-7, rtol=1e-3,
                                       relative_atol=1e-4, min_scale=1e-2)


def test_degenerate_cases_are_finite(device):
    # A particle on a capsule's axis, a zero-length segment (a sphere) with a particle at its centre,
    # a zero radius, and a particle at a segment end.
    x = torch.tensor([[0.0, 0.0, 0.5], [2.0, 2.0, 2.0], [2.1, 2.0, 2.0], [5.0, 5.0, 5.0], [0.0, 0.0, 1.0]],
                     device=device, requires_grad=True)
    start = torch.tensor([[0.0, 0.0, 0.0], [2.0, 2.0, 2.0], [5.0, 5.0, 5.0]], device=device, requires_grad=True)
    end = torch.tensor([[0.0, 0.0, 1.0], [2.0, 2.0, 2.0], [6.0, 5.0, 5.0]], device=device, requires_grad=True)
    radius = torch.tensor([0.3, 0.5, 0.0], device=device, requires_grad=True)
    out = ops.push_out_of_capsules(x, start, end, radius)
    out_ref = reference.push_out_of_capsules(x, start, end, radius)
    torch.testing.assert_close(out, out_ref, rtol=0, atol=1e-6)
    assert torch.isfinite(out).all()
    # on the axis: pushed along a perpendicular of the axis onto the surface
    assert abs(out[0, 2].item() - 0.5) < 1e-6 and abs(out[0, :2].norm().item() - 0.3) < 1e-6
    # the sphere: its centre goes up by the radius; a particle inside goes radially out
    torch.testing.assert_close(out[1], torch.tensor([2.0, 2.0, 2.5], device=device))
    torch.testing.assert_close(out[2], torch.tensor([2.5, 2.0, 2.0], device=device))
    assert torch.equal(out[3], x[3])  # radius 0 holds nothing
    grads = torch.autograd.grad(out, [x, start, end, radius], torch.ones_like(out))
    assert all(torch.isfinite(g).all() for g in grads)


def test_empty_inputs(device):
    scene = random_scene(6, device=device)
    no_capsules = {**scene, "segment_start": scene["segment_start"][:0], "segment_end": scene["segment_end"][:0],
                   "radius": scene["radius"][:0]}
    ours = leaves(no_capsules)
    out = call(ops.push_out_of_capsules, ours)
    assert torch.equal(out, scene["x"])
    grads = torch.autograd.grad(out, [ours[n] for n in NAMES], torch.ones_like(out))
    assert torch.equal(grads[0], torch.ones_like(grads[0])) and grads[3].shape == (0,)
    ours = leaves({**scene, "x": scene["x"][:0]})
    out = call(ops.push_out_of_capsules, ours)
    assert out.shape == (0, 3)
    grads = torch.autograd.grad(out.sum(), [ours[n] for n in NAMES])
    assert all((g == 0).all() for g in grads[1:])


def test_bad_input(device):
    scene = random_scene(7, particle_count=10, capsule_count=3, device=device)

    def with_(**changes):
        return call(ops.push_out_of_capsules, {**scene, **changes})

    with pytest.raises(ValueError, match=r"x must have shape \[\*, 3\]"):
        with_(x=scene["x"][:, :2])
    with pytest.raises(ValueError, match=r"segment_end must have shape \[3, 3\]"):
        with_(segment_end=scene["segment_end"][:2])
    with pytest.raises(ValueError, match=r"radius must have shape \[3\]"):
        with_(radius=scene["radius"][:, None])
    with pytest.raises(TypeError, match="radius must be float32"):
        with_(radius=scene["radius"].double())
    with pytest.raises(TypeError, match="segment_start must be a floating-point tensor"):
        with_(segment_start=scene["segment_start"].int())
    with pytest.raises(TypeError, match="x must be a torch.Tensor"):
        with_(x=scene["x"].tolist())
    if device != "cpu":
        with pytest.raises(ValueError, match="is on cpu"):
            with_(radius=scene["radius"].cpu())
