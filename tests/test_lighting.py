"""The global world-frame lighting term: outward normals, identity start, irradiance values, gradients."""

import math

import torch

from warpavatar.model import PosedGaussians
from warpavatar.extensions.lighting import WorldLighting, outward_normals

HEADS = torch.tensor([[0.0, 0.0, 0.0]])
TAILS = torch.tensor([[0.0, 0.0, 1.0]])  # one bone along +z


def _flat_gaussians(generator, count=64):
    """Flat Gaussians around the bone, each flattened along its radial direction (its true outward normal),
    with random canonical orientations about that normal and random signs of the local axis."""
    angle = torch.rand(count, generator=generator) * 2 * math.pi
    radial = torch.stack([torch.cos(angle), torch.sin(angle), torch.zeros(count)], dim=1)
    means = radial * 0.3 + torch.tensor([0.0, 0.0, 0.5])
    # quaternion taking local +x (or -x) to the radial direction: rotation about z by angle (+ pi for half)
    flip = (torch.rand(count, generator=generator) < 0.5).float() * math.pi
    half = (angle + flip) / 2
    quats = torch.stack([torch.cos(half), torch.zeros(count), torch.zeros(count), torch.sin(half)], dim=1)
    scales = torch.tensor([0.005, 0.05, 0.04]).repeat(count, 1)  # smallest along local x
    return means, quats, scales, radial


def test_outward_normals_point_away_from_the_bone():
    generator = torch.Generator().manual_seed(0)
    means, quats, scales, radial = _flat_gaussians(generator)
    normals = outward_normals(means, quats, quats, scales, HEADS, TAILS)
    assert torch.allclose(normals, radial, atol=1e-5)


def test_normals_turn_with_the_posed_rotation():
    generator = torch.Generator().manual_seed(1)
    means, quats, scales, radial = _flat_gaussians(generator)
    turn = torch.tensor([math.cos(0.4), 0.0, 0.0, math.sin(0.4)])  # 0.8 rad about z
    w1, v1 = turn[:1], turn[1:]
    posed = torch.cat([w1 * quats[:, :1] - (v1 * quats[:, 1:]).sum(-1, keepdim=True),
                       w1 * quats[:, 1:] + quats[:, :1] * v1 + torch.cross(v1.expand_as(quats[:, 1:]), quats[:, 1:],
                                                                           dim=-1)], dim=1)
    normals = outward_normals(means, quats, posed, scales, HEADS, TAILS)
    c, s = math.cos(0.8), math.sin(0.8)
    expected = radial @ torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]).T
    assert torch.allclose(normals, expected, atol=1e-5)


def test_lighting_starts_as_identity_and_learns_a_direction():
    generator = torch.Generator().manual_seed(2)
    means, quats, scales, radial = _flat_gaussians(generator)
    posed = PosedGaussians(means=means, quats=quats, canonical_quats=quats, canonical_means=means, scales=scales)
    colors = torch.rand(means.shape[0], 3, generator=generator) * 0.5 + 0.25
    lighting = WorldLighting(HEADS, TAILS)
    assert torch.equal(lighting.shade(colors, posed), colors)
    with torch.no_grad():
        lighting.ambient.fill_(0.8)
        lighting.directional.copy_(torch.tensor([[0.3, 0.0, 0.0]] * 3))
    expected = colors * (0.8 + 0.3 * radial[:, :1]).clamp_min(0)
    assert torch.allclose(lighting.shade(colors, posed), expected, atol=1e-6)
    # gradients reach the 12 numbers; targets lit from +x pull the directional x terms up
    lighting = WorldLighting(HEADS, TAILS)
    target = colors * (1.0 + 0.5 * radial[:, :1])
    optimizer = torch.optim.Adam(lighting.parameters(), lr=0.05)
    for _ in range(200):
        optimizer.zero_grad()
        ((lighting.shade(colors, posed) - target) ** 2).mean().backward()
        optimizer.step()
    assert torch.allclose(lighting.directional[:, 0], torch.full((3,), 0.5), atol=0.05)
    assert torch.allclose(lighting.ambient, torch.ones(3), atol=0.05)
