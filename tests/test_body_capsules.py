"""Tests of :mod:`warpavatar.sim.capsules`: capsules fitted to Gaussians scattered on cylinders around bones."""

import math

import pytest
import torch

from warpavatar import ops
from warpavatar.geometry import quat_to_matrix
from warpavatar.sim import capsules_near, distance_to_segments, fit_body_capsules, pose_capsules
from warpavatar.sim.capsules import select

HEADS = torch.tensor([[0.0, 0.0, 1.0], [0.2, 0.0, 1.4], [0.1, 0.0, 1.0], [0.5, 0.0, 1.4]])
TAILS = torch.tensor([[0.0, 0.0, 1.5], [0.5, 0.0, 1.4], [0.1, 0.0, 0.5], [0.5, 0.0, 1.4]])  # the last: a point
RADII = torch.tensor([0.15, 0.05, 0.07, 0.04])


def cylinder_points(generator, head, tail, radius, count):
    """Points on the surface of the capsule around ``head``-``tail`` (a sphere for a zero-length bone)."""
    axis = tail - head
    t = torch.rand(count, 1, generator=generator)
    direction = torch.randn(count, 3, generator=generator)
    if axis.norm() > 0:
        unit = axis / axis.norm()
        direction = direction - (direction @ unit)[:, None] * unit  # perpendicular to the bone
    direction = direction / direction.norm(dim=1, keepdim=True)
    noise = 1.0 + 0.01 * torch.randn(count, 1, generator=generator)
    return head + t * axis + radius * noise * direction


def body(seed=0, per_bone=400):
    """Body Gaussians on each bone's cylinder, garment Gaussians 30 % outside the torso's, a few stray ones.

    Returns means [N,3], skinning weights [N,J], a garment mask [N]."""
    generator = torch.Generator().manual_seed(seed)
    joint_count = HEADS.shape[0]
    means, owner, garment = [], [], []
    for joint in range(joint_count):
        means.append(cylinder_points(generator, HEADS[joint], TAILS[joint], RADII[joint], per_bone))
        owner.append(torch.full((per_bone,), joint))
        garment.append(torch.zeros(per_bone, dtype=torch.bool))
    # the garment over the torso, mostly skinned to it
    means.append(cylinder_points(generator, HEADS[0], TAILS[0], 1.3 * RADII[0], per_bone))
    owner.append(torch.zeros(per_bone, dtype=torch.long))
    garment.append(torch.ones(per_bone, dtype=torch.bool))
    # stray Gaussians of the arm that the torso holds too (3 % of its own): the quantile ignores them
    means.append(cylinder_points(generator, HEADS[1], TAILS[1], RADII[1], per_bone // 33))
    owner.append(torch.zeros(per_bone // 33, dtype=torch.long))
    garment.append(torch.zeros(per_bone // 33, dtype=torch.bool))
    means, owner, garment = torch.cat(means), torch.cat(owner), torch.cat(garment)
    weights = 0.3 * torch.rand(means.shape[0], joint_count, generator=generator)
    weights[torch.arange(means.shape[0]), owner] = 2.0 + torch.rand(means.shape[0], generator=generator)
    # a few Gaussians without a dominant bone (weights spread evenly) are left out
    weights[:20] = 1.0
    return means, weights / weights.sum(dim=1, keepdim=True), garment


def test_radii_of_cylinders_are_recovered():
    means, weights, garment = body()
    capsules = fit_body_capsules(HEADS, TAILS, means, weights, exclude=garment)
    torch.testing.assert_close(capsules.segment_start, HEADS)
    torch.testing.assert_close(capsules.segment_end, TAILS)
    torch.testing.assert_close(capsules.radius, RADII, rtol=0.02, atol=0.0)
    # without excluding the garment, the torso's capsule would swell to the garment
    swollen = fit_body_capsules(HEADS, TAILS, means, weights)
    assert swollen.radius[0] > 1.2 * RADII[0]
    # a bone without enough Gaussians holds nothing
    few = fit_body_capsules(HEADS, TAILS, means, weights, exclude=garment, min_points=10_000)
    assert (few.radius == 0).all()


def test_posed_capsules_move_with_their_bones():
    means, weights, garment = body(seed=1)
    capsules = fit_body_capsules(HEADS, TAILS, means, weights, exclude=garment)
    generator = torch.Generator().manual_seed(2)
    quats = torch.randn(HEADS.shape[0], 4, generator=generator)
    transforms = torch.eye(4).repeat(HEADS.shape[0], 1, 1)
    transforms[:, :3, :3] = quat_to_matrix(quats / quats.norm(dim=1, keepdim=True))
    transforms[:, :3, 3] = torch.randn(HEADS.shape[0], 3, generator=generator)
    posed = pose_capsules(capsules, transforms)
    torch.testing.assert_close(posed.radius, capsules.radius)
    # Gaussians posed rigidly by their bone keep their distance to its posed segment
    owner = weights.argmax(dim=1)
    keep = ~garment
    moved = (transforms[owner, :3, :3] @ means[:, :, None])[:, :, 0] + transforms[owner, :3, 3]
    before = distance_to_segments(means[keep], HEADS[owner[keep]], TAILS[owner[keep]])
    after = distance_to_segments(moved[keep], posed.segment_start[owner[keep]], posed.segment_end[owner[keep]])
    torch.testing.assert_close(after, before, rtol=0, atol=1e-5)
    # and the collision op pushes a point inside a posed capsule out of it
    inside = posed.segment_start[2:3] + 0.5 * (posed.segment_end[2:3] - posed.segment_start[2:3])
    pushed = ops.push_out_of_capsules(inside, posed.segment_start[2:3], posed.segment_end[2:3], posed.radius[2:3])
    assert math.isclose((pushed - inside).norm().item(), posed.radius[2].item(), rel_tol=1e-5)


def test_capsules_near_a_garment():
    means, weights, garment = body(seed=3)
    capsules = fit_body_capsules(HEADS, TAILS, means, weights, exclude=garment)
    shirt = means[garment]  # 30 % outside the torso's capsule: 0.045 from its surface
    # the upper arm starts right at the shirt (0.2 from the torso's axis); the torso is 0.045 inside it, the
    # leg's capsule 0.025 below its hem; the zero-length bone at the hand 0.26 away
    assert capsules_near(capsules, shirt, margin=0.0).tolist() == [1]
    assert capsules_near(capsules, shirt, margin=0.035).tolist() == [1, 2]
    wide = capsules_near(capsules, shirt, margin=0.06, chunk=100)
    assert wide.tolist() == [0, 1, 2]
    assert capsules_near(capsules, shirt, margin=0.3).tolist() == [0, 1, 2, 3]
    chosen = select(capsules, wide)
    torch.testing.assert_close(chosen.radius, capsules.radius[wide])
    # posing only the chosen ones with their bones' transforms is posing all, then choosing
    transforms = torch.eye(4).repeat(HEADS.shape[0], 1, 1)
    transforms[:, :3, 3] = torch.arange(HEADS.shape[0] * 3).reshape(-1, 3).float()
    torch.testing.assert_close(pose_capsules(chosen, transforms[wide]).segment_end,
                               pose_capsules(capsules, transforms).segment_end[wide])


def test_bad_input():
    means, weights, garment = body(per_bone=40)
    with pytest.raises(ValueError, match=r"skinning_weights must have shape"):
        fit_body_capsules(HEADS, TAILS, means, weights[:, :3])
    with pytest.raises(ValueError, match=r"exclude must have shape"):
        fit_body_capsules(HEADS, TAILS, means, weights, exclude=garment[:5])
    with pytest.raises(ValueError, match="quantile must be in"):
        fit_body_capsules(HEADS, TAILS, means, weights, quantile=0.0)
    capsules = fit_body_capsules(HEADS, TAILS, means, weights)
    with pytest.raises(ValueError, match=r"bone_transforms must have shape \[4, 4, 4\]"):
        pose_capsules(capsules, torch.eye(4)[None])
