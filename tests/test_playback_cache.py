"""Playback computes once what depends only on a frozen avatar (issue #18): the activated Gaussians and their
skinning weights (:class:`~warpavatar.model.frozen.FrozenCanonical`), the pose correction's parameter-only
pieces, and its network in float16 when the player asks for it. Each cache is held to the per-frame computation
on random parameters, and followed when the parameters change."""

from __future__ import annotations

import math

import pytest
import torch

from warpavatar import _torch_impl as reference
from warpavatar._src.precision import current_mlp_dtype, mlp_dtype
from warpavatar.model.frozen import FrozenCanonical


@pytest.fixture(scope="module")
def demo_video():
    from warpavatar import data

    return data.load_video_folder(data.demo_subject_path() / "train", scale=0.25)


def _randomized(avatar, seed: int, *, correction_std: float = 0.3):
    """The avatar with random Gaussian parameters (unnormalized quaternions, spread scales and opacities) and a
    pose correction with random weights everywhere (its zero-initialized head and frame codes included)."""
    generator = torch.Generator().manual_seed(seed)
    gaussians = avatar.gaussians
    with torch.no_grad():
        for parameter in (gaussians.quats, gaussians.sh_dc, gaussians.sh_rest):
            parameter.copy_(torch.randn(parameter.shape, generator=generator))
        gaussians.log_scales.copy_(-4.0 + torch.randn(gaussians.log_scales.shape, generator=generator))
        gaussians.opacity_logits.copy_(2.0 * torch.randn(gaussians.opacity_logits.shape, generator=generator))
        part = avatar.part("pose_correction")
        for parameter in [] if part is None else part.parameters():
            parameter.copy_(correction_std * torch.randn(parameter.shape, generator=generator))
    return avatar


def _avatar(video, *, frame_codes: int = 0, seed: int = 1):
    from tests.conftest import small_avatar
    from warpavatar.extensions.pose_correction import PoseCorrection

    with torch.enable_grad():  # the field's distillation
        avatar = small_avatar(video.skeleton, seed=seed, per_bone=30, cells=8, distill_steps=5, random_frames=True)
    field = avatar.field
    part = PoseCorrection(field.bbox_min, field.bbox_max, torch.as_tensor(video.skeleton.parents), hidden=24,
                          frame_count=frame_codes, code_width=5)
    if frame_codes:
        part.set_frame_poses(torch.as_tensor(video.bone_transforms[:frame_codes], dtype=torch.float32))
    avatar.add_part(part)
    return _randomized(avatar, seed)


def _bones(video, frame: int) -> torch.Tensor:
    return torch.as_tensor(video.bone_transforms[frame], dtype=torch.float32)


def _frozen(avatar, grid, degree=None):
    frozen = FrozenCanonical()
    frozen.refresh(avatar.gaussians, avatar.field, grid, sh_degree=avatar.gaussians.sh_degree if degree is None
                   else degree)
    return frozen


def _without_parts(video):
    """A random avatar without parts, its skinning grid and its frozen tensors."""
    avatar = _avatar(video)
    avatar.parts.clear()
    grid = avatar.field.grid_weights()
    return avatar, grid, _frozen(avatar, grid)


def _per_frame(avatar, grid, degree):
    gaussians = avatar.gaussians
    return {"quats": gaussians.normalized_quats, "scales": gaussians.scales, "opacities": gaussians.opacities,
            "colors": gaussians.sh_coefficients(degree), "weights": avatar.field.weights(gaussians.means, grid)}


# ------------------------------------------------------------------------------------- the frozen Gaussians
@torch.no_grad()
def test_frozen_tensors_are_the_per_frame_values_and_follow_changes(demo_video):
    avatar, grid, frozen = _without_parts(demo_video)
    expected = _per_frame(avatar, grid, 1)
    assert expected["quats"].norm(dim=-1).std() > 0 and avatar.gaussians.quats.norm(dim=-1).std() > 0.1
    for name, value in expected.items():
        assert torch.equal(getattr(frozen, name), value), name
    storage = frozen.refresh(avatar.gaussians, avatar.field, grid, sh_degree=1)
    held = {name: getattr(frozen, name) for name in expected}

    # in-place changes (an optimizer step, a new grid copied in): refilled in the same storage
    optimizer = torch.optim.SGD(avatar.gaussians.parameters(), lr=0.3)
    for parameter in avatar.gaussians.parameters():
        parameter.grad = torch.randn_like(parameter)
    optimizer.step()
    with torch.no_grad():
        avatar.field.mlp[0].bias.add_(0.7)
        grid.copy_(avatar.field.grid_weights())
    assert frozen.refresh(avatar.gaussians, avatar.field, grid, sh_degree=1) == storage
    expected_after = _per_frame(avatar, grid, 1)
    for name, value in expected_after.items():
        assert getattr(frozen, name) is held[name]
        assert torch.equal(held[name], value) and not torch.equal(value, expected[name]), name

    # a lower degree and fewer Gaussians: new tensors of the new shapes
    keep = torch.arange(avatar.gaussians.count) % 3 != 0
    avatar.gaussians.prune(keep)
    assert frozen.refresh(avatar.gaussians, avatar.field, grid, sh_degree=0) != storage
    for name, value in _per_frame(avatar, grid, 0).items():
        assert torch.equal(getattr(frozen, name), value), name
    assert frozen.colors.shape == (avatar.gaussians.count, 1, 3) and frozen.sh_degree == 0


@torch.no_grad()
def test_posing_from_frozen_tensors_reads_no_activation_again(demo_video):
    from torch.profiler import ProfilerActivity, profile

    avatar, grid, frozen = _without_parts(demo_video)
    bones = _bones(demo_video, 3)
    with profile(activities=[ProfilerActivity.CPU]) as run:
        posed = avatar.pose(bones, grid=grid, frozen=frozen)
    names = {event.name for event in run.events()}
    assert not names & {"aten::exp", "aten::sigmoid", "aten::linalg_vector_norm", "aten::cat"}, names
    assert posed["weights"] is frozen.weights  # no part moved the centres: the kept weights are read
    expected = avatar.pose(bones, grid=grid)
    for name in ("means", "quats", "scales", "opacities", "colors", "weights"):
        assert torch.equal(posed[name], expected[name]), name
    with pytest.raises(ValueError, match="keep SH degree 1, posing asks for 0"):
        avatar.pose(bones, grid=grid, frozen=frozen, sh_degree=0)


# ------------------------------------------------------------------------------- the pose correction's cache
def _close_outputs(ours: torch.Tensor, reference: torch.Tensor) -> None:
    """float16: inputs, weights and each layer's outputs rounded to 11 significant bits: within 1 % of the
    largest output."""
    ours = ours.float()[:, :reference.shape[1]]
    torch.testing.assert_close(ours, reference, rtol=0, atol=0.01 * float(reference.abs().max()))
    assert not torch.equal(ours, reference)


@pytest.mark.parametrize("frame_codes", [0, 4])
@torch.no_grad()
def test_cached_pose_correction_equals_the_per_frame_one(demo_video, frame_codes):
    avatar = _avatar(demo_video, frame_codes=frame_codes, seed=2 + frame_codes)
    part = avatar.parts["pose_correction"]
    means = avatar.gaussians.means
    grid = avatar.field.grid_weights()
    frozen = _frozen(avatar, grid)
    part.prepare_playback(means, mlp_dtype=torch.float16)
    assert part._network.half is not None
    for frame in (0, 2, 7):  # training instants (with their codes) and another pose
        bones = _bones(demo_video, frame)
        expected = avatar.pose(bones, grid=grid)  # outside a player's frame: the fit's code
        code = part.frame_code(bones) if frame_codes else None
        reference = part._outputs(means, bones, code)
        assert reference.abs().max() > 1.0  # the random weights make a large correction
        with mlp_dtype(torch.float32):
            network = part._playback_network(means)
            ours = part._outputs(means, bones, code, network=network)  # the frame bias from two kernels
            torch.testing.assert_close(ours, reference, rtol=1e-5, atol=1e-5 * float(reference.abs().max()))
            ours = avatar.pose(bones, grid=grid, frozen=frozen)
        assert ours["weights"] is not frozen.weights  # the correction moved the centres: read there
        for name in ("means", "quats", "scales", "weights"):  # kernels instead of torch's ops: float32 rounding
            torch.testing.assert_close(ours[name], expected[name], rtol=1e-5, atol=1e-5, msg=name)
        with mlp_dtype(torch.float16):
            half = part._outputs(means, bones, code, network=part._playback_network(means))
            posed_half = avatar.pose(bones, grid=grid, frozen=frozen)
        assert half.dtype == torch.float16 and half.shape[1] == 16 and not half[:, 9:].any()  # padded with zeros
        _close_outputs(half, reference)
        offset = float(reference[:, :3].abs().max() * part._offset_scale())  # the largest offset [world units]
        torch.testing.assert_close(posed_half["means"], expected["means"], rtol=0, atol=0.01 * offset)


@torch.no_grad()
def test_float16_network_runs_only_inside_a_float16_block_and_follows_changes(demo_video):
    avatar = _avatar(demo_video, seed=5)
    part = avatar.parts["pose_correction"]
    means, bones = avatar.gaussians.means, _bones(demo_video, 4)
    part.prepare_playback(means, mlp_dtype=torch.float16)
    network = part._network
    storage = part.prepare_playback(means, mlp_dtype=torch.float32)  # another player's float32: kept as it is
    assert part._network is network and network.half is not None
    assert current_mlp_dtype() is None and part._playback_network(means) is None  # outside a player's frame
    reference = part._outputs(means, bones, None)
    with mlp_dtype(torch.float32):
        full = part._outputs(means, bones, None, network=part._playback_network(means))
    torch.testing.assert_close(full, reference, rtol=1e-5, atol=1e-5 * float(reference.abs().max()))
    with mlp_dtype(torch.float16):
        before = part._outputs(means, bones, None, network=part._playback_network(means))
    _close_outputs(before, reference)
    # a change of the weights: the cache no longer serves, and is refilled in place by the next preparation
    part.trunk[2].weight.mul_(1.5)
    with mlp_dtype(torch.float16):
        assert part._playback_network(means) is None
    assert part.prepare_playback(means, mlp_dtype=torch.float16) == storage
    with mlp_dtype(torch.float16):
        after = part._outputs(means, bones, None, network=part._playback_network(means))
    _close_outputs(after, part._outputs(means, bones, None))
    assert (after - before).abs().max() > 0.1


@torch.no_grad()
def test_float16_is_not_used_where_activations_could_leave_its_range(demo_video):
    avatar = _avatar(demo_video, seed=6)
    part = avatar.parts["pose_correction"]
    means = avatar.gaussians.means
    part.prepare_playback(means, mlp_dtype=torch.float16)
    peak = part._network.peak
    assert 1.0 < peak < 65504.0 / 16.0
    factor = 65504.0 / 16.0 / peak * 1.5  # the third layer's outputs: 1.5 times the margin below float16's largest
    part.trunk[4].weight.mul_(factor)
    part.prepare_playback(means, mlp_dtype=torch.float16)
    network = part._network
    assert network.half_asked and network.half is None
    bones = _bones(demo_video, 1)
    with mlp_dtype(torch.float16):
        ours = part._outputs(means, bones, None, network=part._playback_network(means))
    assert ours.dtype == torch.float32  # the float32 network
    reference = part._outputs(means, bones, None)
    torch.testing.assert_close(ours, reference, rtol=1e-5, atol=1e-5 * float(reference.abs().max()))
    part.trunk[4].weight.div_(factor)
    part.prepare_playback(means, mlp_dtype=torch.float16)
    assert part._network.half is not None


@pytest.mark.parametrize("outputs_dtype", [torch.float32, torch.float16])
def test_correction_kernel_matches_the_torch_code(device, outputs_dtype):
    from warpavatar import ops
    from warpavatar.extensions.pose_correction import corrected_gaussians

    generator = torch.Generator().manual_seed(3)
    count = 1000
    outputs = (2.0 * torch.randn(count, 9, generator=generator)).to(outputs_dtype)
    outputs[:5, 6:9] = torch.tensor([-5.0, 4.0, 3.5]).to(outputs_dtype)  # beyond the log-scale clamp
    quats = torch.randn(count, 4, generator=generator)
    quats = quats / quats.norm(dim=-1, keepdim=True)
    means, scales = torch.randn(count, 3, generator=generator), 0.01 + torch.rand(count, 3, generator=generator)
    offset_scale = torch.tensor(0.37)
    inputs = [t.to(device) for t in (outputs, means, quats, scales, offset_scale)]
    expected = corrected_gaussians(inputs[0].float(), *inputs[1:])
    with torch.no_grad():
        ours = ops.apply_correction(*inputs)
    for name, a, b, c in zip(("means", "quats", "scales"), ours, expected, reference.apply_correction(*inputs)):
        assert a.dtype == torch.float32 and a.device == b.device
        torch.testing.assert_close(a, b, rtol=1e-6, atol=1e-6, msg=name)
        assert torch.equal(c, b), name  # the reference is the fit's code
    empty = [t[:0] for t in inputs[:4]]
    with torch.no_grad():
        assert [t.shape for t in ops.apply_correction(*empty, inputs[4])] == [(0, 3), (0, 4), (0, 3)]
    with pytest.raises(ValueError, match="no gradients"):
        ops.apply_correction(inputs[0], inputs[1].requires_grad_(), *inputs[2:])
    with torch.no_grad():  # columns past the 9th (a padded network's zeros) are not read
        padded = torch.cat([inputs[0], torch.full_like(inputs[0][:, :7], 1e3)], dim=1)
        assert all(torch.equal(a, b) for a, b in zip(ops.apply_correction(padded, *inputs[1:]), ours))
    with torch.no_grad(), pytest.raises(ValueError, match="outputs must have at least 9 columns, got 8"):
        ops.apply_correction(inputs[0][:, :8], *inputs[1:])


def test_frame_code_kernels_give_the_torch_code(device):
    from tests.test_mlp_paths import _random_correction, _random_poses
    from warpavatar import ops

    part = _random_correction(device, frame_count=6, seed=9)
    generator = torch.Generator().manual_seed(4)
    poses = _random_poses(6, generator).to(device)
    part.set_frame_poses(poses)
    grown = torch.eye(4, device=device).repeat(3, 1, 1)  # grown joints' transforms after the skeleton's
    near = poses[4] + 1e-4 * (torch.rand(poses[4].shape, generator=generator).to(device) - 0.5)  # within 5e-5
    cases = [poses[2], poses[5], near, poses[1] + 3e-4, _random_poses(1, generator)[0].to(device),
             torch.cat([poses[3], grown])]
    with torch.no_grad():
        for pose in cases:
            ours = ops.match_frame_code(part.frame_poses, pose, part.frame_codes)
            assert torch.equal(ours, part.frame_code(pose))
            assert torch.equal(reference.match_frame_code(part.frame_poses, pose, part.frame_codes), ours)
        assert ops.match_frame_code(part.frame_poses, near, part.frame_codes).abs().max() > 0.1  # a match
        assert not ops.match_frame_code(part.frame_poses, poses[1] + 3e-4, part.frame_codes).any()  # none


def test_frame_code_kernels_take_the_first_of_tied_frames_among_many(device):
    # More training frames than a block has threads, two of them the same pose: the earlier one's code.
    from tests.test_mlp_paths import _random_correction, _random_poses
    from warpavatar import ops

    part = _random_correction(device, frame_count=150, seed=11)
    poses = _random_poses(150, torch.Generator().manual_seed(5)).to(device)
    poses[137] = poses[71]
    part.set_frame_poses(poses)
    with torch.no_grad():
        for frame in (71, 137, 149, 3):
            ours = ops.match_frame_code(part.frame_poses, poses[frame], part.frame_codes)
            assert torch.equal(ours, part.frame_code(poses[frame]))
            expected = part.frame_codes[71 if frame == 137 else frame]
            assert torch.equal(ours, expected) and expected.abs().max() > 0


@pytest.mark.parametrize("frame_count", [0, 4])
def test_frame_bias_kernels_give_the_torch_bias(device, frame_count):
    from tests.test_mlp_paths import _random_correction, _random_poses
    from warpavatar import ops
    from warpavatar.extensions.pose_correction import relative_rotations_6d

    part = _random_correction(device, frame_count=frame_count, seed=10 + frame_count)
    generator = torch.Generator().manual_seed(5)
    first, width = part.trunk[0], part.position_width
    parents = part.parents
    index = torch.where(parents >= 0, parents, torch.arange(parents.shape[0], device=device)).int()
    columns = first.weight[:, width:].contiguous()
    bound = torch.full((first.out_features,), 0.3, device=device)
    for pose in _random_poses(3, generator).to(device):
        pose = torch.cat([pose, torch.eye(4, device=device)[None]])  # a grown joint's transform after the skeleton's
        code = part.frame_codes[1] if frame_count else None
        with torch.no_grad():
            feature = part.pose_encoder(relative_rotations_6d(pose[: parents.shape[0]], parents))
            feature = feature if code is None else torch.cat([feature, code])
            expected = torch.addmv(first.bias, first.weight[:, width:], feature)
            unbounded = torch.full_like(bound, float("inf"))
            ours = ops.frame_bias(pose, index, part.pose_encoder.weight, part.pose_encoder.bias, code, columns,
                                  first.bias, low=-unbounded, high=unbounded)
            clamped = ops.frame_bias(pose, index, part.pose_encoder.weight, part.pose_encoder.bias, code, columns,
                                     first.bias, low=-bound, high=bound, dtype=torch.float16)
        assert expected.abs().max() > 1.0 and (expected.abs() > 0.3).any() and (expected.abs() < 0.3).any()
        torch.testing.assert_close(ours, expected, rtol=1e-5, atol=1e-5)
        with torch.no_grad():
            theirs = reference.frame_bias(pose, index, part.pose_encoder.weight, part.pose_encoder.bias, code,
                                          columns, first.bias, low=-bound, high=bound, dtype=torch.float16)
        assert theirs.dtype == torch.float16 and (theirs != clamped).sum() <= 2  # a float16 rounding apart
        assert clamped.dtype == torch.float16
        torch.testing.assert_close(clamped.float(), expected.clamp(-0.3, 0.3), rtol=1e-3, atol=1e-4)
    with pytest.raises(TypeError, match="parent_index must be int32"):
        ops.frame_bias(pose, index.long(), part.pose_encoder.weight, part.pose_encoder.bias, code, columns,
                       first.bias, low=-bound, high=bound)


# ---------------------------------------------------------------------------------------------- the player
def _psnr(a: torch.Tensor, b: torch.Tensor) -> float:
    return 10.0 * math.log10(1.0 / float(((a - b) ** 2).mean()))


def test_player_float16_draws_within_rounding_of_float32(demo_video):
    from warpavatar.model.playback import Player

    avatar = _avatar(demo_video, frame_codes=3, seed=7)
    _randomized(avatar, 7, correction_std=0.1)
    players = {dtype: Player(avatar, demo_video.cameras[0], cuda_graph="off", mlp_dtype=dtype)
               for dtype in ("float32", "float16")}
    assert Player(avatar, demo_video.cameras[0], cuda_graph="off").mlp_dtype == "float32"  # the CPU default
    with pytest.raises(ValueError, match="mlp_dtype must be 'float16' or 'float32', got 'bfloat16'"):
        Player(avatar, demo_video.cameras[0], mlp_dtype="bfloat16")
    for frame in (1, 5, 8):
        bones, camera = _bones(demo_video, frame), demo_video.cameras[frame]
        full = players["float32"].render(bones, camera=camera)[0].clone()
        half = players["float16"].render(bones, camera=camera)[0].clone()
        with torch.no_grad():
            expected = avatar.render(camera, bones)[0]  # outside the player: float32, whatever was prepared
        assert expected.max() > 0.2  # the player's float32: the correction's kernel rounds unlike torch's ops
        torch.testing.assert_close(full, expected, rtol=0, atol=1e-5)
        assert not torch.equal(half, full)
        assert (half - full).abs().max() < 0.05 and _psnr(half, full) > 50.0
    assert avatar.parts["pose_correction"]._network.half is not None


def test_player_follows_in_place_changes_of_the_gaussians_and_the_field(demo_video):
    from warpavatar.model.playback import Player

    avatar = _avatar(demo_video, seed=8)
    _randomized(avatar, 8, correction_std=0.05)
    player = Player(avatar, demo_video.cameras[0], cuda_graph="off", mlp_dtype="float32", check_every=1)
    bones = _bones(demo_video, 6)
    before = player.render(bones)[0].clone()
    frozen = player._frozen
    storage = [frozen.opacities.data_ptr(), frozen.weights.data_ptr()]
    gaussians = avatar.gaussians
    with torch.no_grad():  # what an optimizer step does: every parameter changed in place
        gaussians.opacity_logits.sub_(1.0)
        gaussians.log_scales.add_(0.3)
        gaussians.sh_dc.mul_(0.5)
        gaussians.quats[:, 0].add_(0.5)
        avatar.field.mlp[0].bias.add_(0.5)
    after = player.render(bones)[0]
    with torch.no_grad():
        expected = avatar.render(demo_video.cameras[0], bones)[0]
    torch.testing.assert_close(after, expected, rtol=0, atol=1e-5)
    assert (after - before).abs().max() > 0.1
    assert [frozen.opacities.data_ptr(), frozen.weights.data_ptr()] == storage  # refilled in place
