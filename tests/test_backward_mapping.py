"""TAGA's backward mapping: divergence, bone frames, GMM detection, correction, inverse LBS and cycle losses."""

import math

import pytest
import torch

from warpavatar import ops
from warpavatar.extensions.backward_mapping import BackwardMapping, BoneGMM, bone_axes, jensen_shannon
from warpavatar.model.skinning_field import VoxelSkinningField


def _random_distributions(rows, columns, generator, *, sparse=False):
    values = torch.rand(rows, columns, generator=generator, dtype=torch.float64) + 0.05
    if sparse:  # some exact zeros, as sparse skinning weights have
        values = values * (torch.rand(rows, columns, generator=generator, dtype=torch.float64) > 0.5)
        values[:, 0] += 0.1
    return values / values.sum(-1, keepdim=True)


def _reference_jsd(p, q):
    total = torch.zeros(p.shape[0], dtype=torch.float64)
    for i in range(p.shape[0]):
        for j in range(p.shape[1]):
            m = 0.5 * (p[i, j] + q[i, j])
            if p[i, j] > 0:
                total[i] += 0.5 * p[i, j] * math.log2(p[i, j] / m)
            if q[i, j] > 0:
                total[i] += 0.5 * q[i, j] * math.log2(q[i, j] / m)
    return total


def test_jensen_shannon_matches_definition(device):
    generator = torch.Generator().manual_seed(1)
    p = _random_distributions(30, 7, generator, sparse=True)
    q = _random_distributions(30, 7, generator, sparse=True)
    expected = _reference_jsd(p, q)
    got = jensen_shannon(p.float().to(device), q.float().to(device)).cpu().double()
    assert torch.allclose(got, expected, atol=1e-5)
    assert torch.allclose(jensen_shannon(q.to(device), p.to(device)).cpu(), expected, atol=1e-9)  # symmetric
    assert float(jensen_shannon(p.to(device), p.to(device)).abs().max()) < 1e-9
    one_hot = torch.eye(4, device=device)
    # disjoint supports: exactly one bit
    assert torch.allclose(jensen_shannon(one_hot, one_hot.roll(1, dims=1)), torch.ones(4, device=device))


def test_bone_axes_are_orthonormal_frames_along_the_bone(device):
    generator = torch.Generator().manual_seed(2)
    heads = torch.randn(6, 3, generator=generator).to(device)
    tails = heads + torch.randn(6, 3, generator=generator).to(device)
    tails[5] = heads[5]  # zero length: the z axis
    axes = bone_axes(heads, tails)
    identity = torch.eye(3, device=device).expand(6, 3, 3)
    assert torch.allclose(axes @ axes.transpose(1, 2), identity, atol=1e-5)
    direction = (tails[:5] - heads[:5]) / (tails[:5] - heads[:5]).norm(dim=-1, keepdim=True)
    assert torch.allclose(axes[:5, 0], direction, atol=1e-5)
    assert torch.allclose(axes[5, 0], torch.tensor([0.0, 0.0, 1.0], device=device))


def _three_bone_scene(device, *, seed=0):
    """A chain of three bones along x (0 -> 1 -> 2), points around each, and rigid poses."""
    generator = torch.Generator().manual_seed(seed)
    heads = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    tails = torch.tensor([[1.0, 0.0, 0.0], [2.0, 0.0, 0.0], [3.0, 0.0, 0.0]])
    parents = torch.tensor([-1, 0, 1])
    per_bone = 200
    points, owners = [], []
    for bone in range(3):
        local = torch.rand(per_bone, 3, generator=generator) * torch.tensor([0.8, 0.3, 0.3]) \
            + torch.tensor([0.1, -0.15, -0.15])
        points.append(local + heads[bone])
        owners.append(torch.full((per_bone,), bone))
    points, owners = torch.cat(points), torch.cat(owners)
    weights = torch.nn.functional.one_hot(owners, 3).float() * 0.9 + 0.1 / 3
    return (heads.to(device), tails.to(device), parents.to(device), points.to(device), owners.to(device),
            weights.to(device), generator)


def _rotation(axis, angle):
    axis = torch.tensor(axis, dtype=torch.float32)
    axis = axis / axis.norm()
    skew = torch.tensor([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return torch.eye(3) + math.sin(angle) * skew + (1 - math.cos(angle)) * skew @ skew


def _chain_pose(device):
    """Bone 0 fixed, bone 1 bent 30 degrees about its head, bone 2 following bone 1 and bent 20 more."""
    transforms = torch.eye(4).repeat(3, 1, 1)
    for bone, angle in ((1, 0.5), (2, 0.85)):
        rotation = _rotation([0.0, 0.0, 1.0], angle)
        pivot = torch.tensor([float(bone), 0.0, 0.0])
        transforms[bone, :3, :3] = rotation
        transforms[bone, :3, 3] = pivot - rotation @ pivot
    # bone 2 must also ride on bone 1: compose so its head stays at bone 1's posed tail
    tail_of_1 = transforms[1, :3, :3] @ torch.tensor([2.0, 0.0, 0.0]) + transforms[1, :3, 3]
    transforms[2, :3, 3] = tail_of_1 - transforms[2, :3, :3] @ torch.tensor([2.0, 0.0, 0.0])
    return transforms.to(device)


def _mislabelled(device, *, seed, count):
    """The three-bone scene posed by its true weights, with ``count`` bone-0 Gaussians whose canonical model is
    wrong: skinned by bone 2, at the canonical place that bone-2 skinning maps onto the right observation (the
    training view renders right, the skinning is wrong: an ambiguous Gaussian)."""
    heads, tails, parents, points, owners, weights, generator = _three_bone_scene(device, seed=seed)
    bones = _chain_pose(device)
    posed, _ = ops.lbs(points, weights, bones)
    wrong = torch.nonzero(owners == 0).squeeze(1)[torch.randperm(200, generator=generator)[:count].to(device)]
    bad_weights = weights.clone()
    bad_weights[wrong] = torch.tensor([0.02, 0.03, 0.95], device=device)
    canonical = points.clone()
    canonical[wrong], _ = ops.inverse_lbs(posed[wrong].contiguous(), bad_weights[wrong].contiguous(), bones)
    return heads, tails, parents, points, canonical, posed, bad_weights, bones, wrong, generator


def test_detection_finds_the_mislabelled_gaussians(device):
    heads, tails, parents, _, _, posed, weights, bones, wrong, _ = _mislabelled(device, seed=0, count=20)
    mapping = BackwardMapping(heads, tails, parents, threshold=0.5, neighbours=8, min_semi_axis=0.01)
    ambiguous, estimate = mapping.detect(posed, weights, bones)
    flagged = set(torch.nonzero(ambiguous).squeeze(1).tolist())
    assert set(wrong.tolist()) <= flagged
    assert len(flagged) <= 30, len(flagged)  # few false alarms
    assert torch.allclose(estimate.sum(-1), torch.ones(len(posed), device=device), atol=1e-5)
    # the GMM's estimate itself says "bone 0" where they are seen
    assert bool((estimate[wrong].argmax(-1) == 0).all())


def test_refresh_corrects_weights_and_maps_back_exactly(device):
    heads, tails, parents, points, canonical, posed, weights, bones, wrong, generator = _mislabelled(
        device, seed=3, count=15)
    # the canonical centres the constraints pull carry an offset applied before skinning (a pose correction)
    offset = torch.randn(points.shape, generator=generator).to(device) * 0.01
    mapping = BackwardMapping(heads, tails, parents, threshold=0.5, min_semi_axis=0.01)
    count = mapping.refresh(canonical - offset, posed, weights, bones)
    assert count == mapping.index.numel() >= 15
    assert set(wrong.tolist()) <= set(mapping.index.tolist())
    at_wrong = torch.isin(mapping.index, wrong)
    # the corrected weights are those of a bone-0 neighbour (the true ones), so the corrected canonical centre is
    # where the Gaussian truly belongs
    assert bool((mapping.target_weights[at_wrong].argmax(-1) == 0).all())
    order = torch.argsort(mapping.index[at_wrong])
    assert torch.allclose(mapping.target_means[at_wrong][order] + offset[torch.sort(wrong).values],
                          points[torch.sort(wrong).values], atol=1e-4)
    # skinning the corrected position (offset included) with the corrected weights lands on the observation
    reposed, _ = ops.lbs(mapping.target_means + offset[mapping.index], mapping.target_weights, bones)
    assert torch.allclose(reposed, posed[mapping.index], atol=1e-4)


def test_max_move_drops_far_corrections(device):
    heads, tails, parents, _, canonical, posed, weights, bones, _, _ = _mislabelled(device, seed=4, count=10)
    free = BackwardMapping(heads, tails, parents, min_semi_axis=0.01)
    free.refresh(canonical, posed, weights, bones)
    moves = (free.target_means - canonical[free.index]).norm(dim=-1)
    limit = float(moves.max()) * 0.5
    capped = BackwardMapping(heads, tails, parents, min_semi_axis=0.01, max_move=limit)
    capped.refresh(canonical, posed, weights, bones)
    assert capped.index.numel() == int((moves <= limit).sum()) < free.index.numel()
    assert float((capped.target_means - canonical[capped.index]).norm(dim=-1).max()) <= limit + 1e-6


def test_cycle_losses_values_and_gradients(device):
    generator = torch.Generator().manual_seed(5)
    joint_count = 3
    field = VoxelSkinningField(torch.zeros(3), torch.ones(3), joint_count, cells=8, min_cells=4, hidden=16,
                               layers=2, frequencies=2).to(device)
    mapping = BackwardMapping(torch.rand(joint_count, 3), torch.rand(joint_count, 3), torch.tensor([-1, 0, 1]))
    means = torch.rand(50, 3, generator=generator).to(device).requires_grad_(True)
    zero_geo, zero_skin = mapping.losses(means, field)
    assert float(zero_geo.detach()) == 0.0 and float(zero_skin.detach()) == 0.0  # nothing cached yet
    index = torch.tensor([3, 7, 11, 20], device=device)
    targets = torch.rand(4, 3, generator=generator).to(device)
    target_weights = torch.softmax(torch.randn(4, joint_count, generator=generator), -1).to(device)
    mapping.load_state({"index": index, "target_means": targets, "target_weights": target_weights}, device=device)
    geo, skin = mapping.losses(means, field)
    expected_geo = (means[index] - targets).abs().sum(-1).mean()
    expected_skin = ((field.weights(targets) - target_weights) ** 2).sum(-1).mean()
    assert torch.allclose(geo, expected_geo) and torch.allclose(skin, expected_skin)
    (geo + skin).backward()
    touched = torch.zeros(50, dtype=torch.bool, device=device)
    touched[index] = True
    assert float(means.grad[~touched].abs().max()) == 0.0
    assert bool((means.grad[touched].abs().sum(-1) > 0).all())
    assert any(p.grad is not None and float(p.grad.abs().max()) > 0 for p in field.parameters())
    # file round trip
    again = BackwardMapping(torch.rand(joint_count, 3), torch.rand(joint_count, 3), torch.tensor([-1, 0, 1]))
    again.load_state(mapping.state(), device=device)
    assert torch.equal(again.index, index) and torch.equal(again.target_means, targets)
    mapping.clear()
    assert not mapping.ready and mapping.state() is None


def test_gmm_semi_axes_follow_the_points(device):
    heads, tails, parents, points, owners, weights, _ = _three_bone_scene(device, seed=6)
    gmm = BoneGMM(heads, tails, parents, min_semi_axis=0.001)
    gmm.fit(points, weights, use=torch.ones(len(points), dtype=torch.bool, device=device), weight_floor=0.2,
            percentile=0.85)
    # points fill [0.1, 0.9] along each bone (centre 0.5) and +-0.15 across: 85th percentile of |offset|
    assert torch.allclose(gmm.semi_axes[:, 0], torch.full((3,), 0.34, device=device), atol=0.04)
    assert torch.allclose(gmm.semi_axes[:, 1:], torch.full((3, 2), 0.1275, device=device), atol=0.02)
    estimate = gmm.estimate(points)
    assert float((estimate.argmax(-1) == owners).float().mean()) > 0.97


def test_bad_options_are_clear_errors():
    with pytest.raises(ValueError, match="threshold"):
        BackwardMapping(torch.rand(2, 3), torch.rand(2, 3), torch.tensor([-1, 0]), threshold=1.5)
    with pytest.raises(ValueError, match="neighbours"):
        BackwardMapping(torch.rand(2, 3), torch.rand(2, 3), torch.tensor([-1, 0]), neighbours=0)
