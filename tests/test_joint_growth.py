"""ToMiE's skeleton growth: motion kernels, parent localization, the extra joint book, the field's new outputs,
avatar files and exports, and a fit that grows joints and resumes exactly."""

import math

import numpy as np
import pytest
import torch

from conftest import small_avatar
from warpavatar import data, ops
from warpavatar.extensions.joint_growth import (ExtraJoints, assignment_weights, joint_gradient_sums,
                                                joint_gradients, locate_parents, motion_kernel)
from warpavatar.fit import preset
from warpavatar.geometry import quat_from_vector, quat_to_matrix
from warpavatar.model import Avatar
from warpavatar.model.skinning_field import bone_distance_prior


def _random_rigid(count, generator, *, spread=0.3):
    transforms = torch.eye(4).repeat(count, 1, 1)
    for k in range(count):
        q, _ = torch.linalg.qr(torch.randn(3, 3, generator=generator))
        transforms[k, :3, :3] = q * torch.sign(torch.det(q))
        transforms[k, :3, 3] = torch.randn(3, generator=generator) * spread
    return transforms


def _axis_quaternion(axis, angle):
    axis = torch.as_tensor(axis, dtype=torch.float32)
    axis = axis / axis.norm()
    return torch.cat([torch.tensor([math.cos(angle / 2)]), math.sin(angle / 2) * axis])


# ----------------------------------------------------------------------------------------- localization
def test_motion_kernel_matches_float64_loops(device):
    generator = torch.Generator().manual_seed(0)
    posed_means = torch.randn(7, 30, 3, generator=generator)
    posed_joints = torch.randn(7, 5, 3, generator=generator)
    kernel = motion_kernel(posed_means.to(device), posed_joints.to(device)).cpu()
    means, joints = posed_means.double().numpy(), posed_joints.double().numpy()
    expected = np.zeros((30, 5))
    for i in range(30):
        for k in range(5):
            distances = np.linalg.norm(means[:, i] - joints[:, k], axis=-1)
            expected[i, k] = np.mean((distances - distances.mean()) ** 2)
    assert kernel.dtype == torch.float32
    np.testing.assert_allclose(kernel.numpy(), expected, rtol=1e-5, atol=1e-7)


def test_motion_kernel_is_zero_for_a_rigidly_attached_point(device):
    generator = torch.Generator().manual_seed(1)
    joints = torch.randn(2, 3, generator=generator)
    points = torch.randn(4, 3, generator=generator)
    posed_means, posed_joints = [], []
    for transform in _random_rigid(6, generator):
        other = _random_rigid(1, generator)[0]  # joint 1 moves independently of the points
        posed_means.append(points @ transform[:3, :3].T + transform[:3, 3])
        posed_joints.append(torch.stack([transform[:3, :3] @ joints[0] + transform[:3, 3],
                                         other[:3, :3] @ joints[1] + other[:3, 3]]))
    kernel = motion_kernel(torch.stack(posed_means).to(device), torch.stack(posed_joints).to(device)).cpu()
    assert kernel[:, 0].abs().max() < 1e-5
    assert kernel[:, 1].min() > 1e-3


def test_assignment_mixes_inverse_kernel_and_lbs(device):
    generator = torch.Generator().manual_seed(2)
    kernel = torch.rand(20, 4, generator=generator).to(device) * 0.1
    lbs = torch.softmax(torch.randn(20, 4, generator=generator), dim=-1).to(device)
    mixed = assignment_weights(kernel, lbs, mix=0.4, floor=1e-4)
    assert torch.allclose(mixed.sum(-1), torch.ones(20, device=device), atol=1e-6)
    assert torch.allclose(assignment_weights(kernel, lbs, mix=0.0, floor=1e-4), lbs)
    inverse = 1.0 / (kernel + 1e-4)
    assert torch.allclose(assignment_weights(kernel, lbs, mix=1.0, floor=1e-4), inverse / inverse.sum(-1, keepdim=True))
    # the joint a point moves least relative to takes the largest motion-kernel share
    assert torch.equal(assignment_weights(kernel, lbs, mix=1.0, floor=1e-4).argmax(-1), kernel.argmin(-1))
    with pytest.raises(ValueError, match="mix"):
        assignment_weights(kernel, lbs, mix=1.5, floor=1e-4)


def test_joint_gradients_and_parent_localization(device):
    generator = torch.Generator().manual_seed(3)
    assignment = torch.softmax(torch.randn(50, 6, generator=generator) * 3, dim=-1).to(device)
    gradient = torch.rand(50, generator=generator).to(device)
    result = joint_gradients(gradient, assignment)
    expected = (assignment * gradient[:, None]).sum(0) / assignment.sum(0)
    assert torch.allclose(result, expected)
    values = torch.tensor([1.0, 5.0, 0.9, 3.1, 1.1, 0.2], device=device)  # median 1.0
    assert locate_parents(values, ratio=3.0, max_count=4).tolist() == [1, 3]
    assert locate_parents(values, ratio=3.0, max_count=1).tolist() == [1]
    assert locate_parents(values, ratio=10.0, max_count=4).numel() == 0


def test_pooled_joint_gradients_add_up_over_rounds(device):
    generator = torch.Generator().manual_seed(7)
    assignment = torch.softmax(torch.randn(40, 5, generator=generator) * 2, dim=-1).to(device)
    sums = torch.rand(40, generator=generator).to(device) * 10
    seen = torch.full((40,), 10.0, device=device)
    numerator, denominator = joint_gradient_sums(sums, seen, assignment)
    # equal visibility: Eq. 4 of the per-point means
    assert torch.allclose(numerator / denominator, joint_gradients(sums / seen, assignment), atol=1e-6)
    # two rounds with different points pool into the statistics of all (point, step) pairs at once
    other = torch.softmax(torch.randn(25, 5, generator=generator), dim=-1).to(device)
    other_sums = torch.rand(25, generator=generator).to(device) * 3
    other_seen = torch.randint(1, 9, (25,), generator=generator).float().to(device)
    a, b = joint_gradient_sums(other_sums, other_seen, other)
    whole = joint_gradient_sums(torch.cat([sums, other_sums]), torch.cat([seen, other_seen]),
                                torch.cat([assignment, other]))
    assert torch.allclose(numerator + a, whole[0], atol=1e-5)
    assert torch.allclose(denominator + b, whole[1], atol=1e-5)
    with pytest.raises(ValueError, match="must agree"):
        joint_gradient_sums(sums, seen[:3], assignment)


def test_localization_finds_the_joint_whose_points_underfit(device):
    """Points around joint 2 carry large gradients: joint 2, and only it, is located."""
    generator = torch.Generator().manual_seed(4)
    heads = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 0.5], [0.0, 0.0, 1.0], [0.3, 0.0, 1.0]])
    tails = torch.tensor([[0.0, 0.0, 0.5], [0.0, 0.0, 1.0], [0.0, 0.0, 1.4], [0.6, 0.0, 1.0]])
    points = ((heads + tails)[:, None] * 0.5 + 0.05 * torch.randn(4, 40, 3, generator=generator)).reshape(-1, 3)
    weights = bone_distance_prior(points, heads, tails, temperature=0.02)
    bones = torch.stack([_random_rigid(4, generator, spread=0.1) for _ in range(12)])  # [T,J,4,4]
    posed_means = torch.stack([ops.lbs(points.to(device), weights.to(device), b.to(device))[0] for b in bones])
    posed_joints = torch.einsum("tjab,jb->tja", bones[..., :3, :3], heads) + bones[..., :3, 3]
    kernel = motion_kernel(posed_means, posed_joints.to(device))
    assignment = assignment_weights(kernel, weights.to(device), mix=0.4, floor=1e-4)
    gradient = 0.1 + 0.05 * torch.rand(160, generator=generator)
    gradient[80:120] *= 8.0  # the Gaussians around bone 2
    per_joint = joint_gradients(gradient.to(device), assignment)
    assert locate_parents(per_joint, ratio=2.0, max_count=4).tolist() == [2]


# ------------------------------------------------------------------------------------- extra joint book
def _extra_joints(device, *, frame_count=5, joint_count=3, seed=5):
    generator = torch.Generator().manual_seed(seed)
    poses = torch.stack([_random_rigid(joint_count, generator) for _ in range(frame_count)])
    heads = torch.randn(joint_count, 3, generator=generator)
    parents = torch.tensor([2, 0])
    extra = ExtraJoints(parents, heads[parents], poses, torch.arange(frame_count) / 30.0, extent=1.0,
                        hidden_position=16, hidden_rotation=16, layers=2).to(device)
    with torch.no_grad():  # a trained book: rotations far from the identity
        for module in (extra.position_mlp[-1], extra.rotation_mlp[-1]):
            module.weight.copy_(torch.randn(module.weight.shape, generator=generator) * 0.5)
            module.bias.copy_(torch.randn(module.bias.shape, generator=generator) * 0.5)
    return extra, poses.to(device), generator


def test_quaternion_helpers():
    q = _axis_quaternion([0.0, 0.0, 1.0], 0.8)
    c, s = math.cos(0.8), math.sin(0.8)
    assert torch.allclose(quat_to_matrix(q), torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]),
                          atol=1e-6)
    assert torch.equal(quat_from_vector(torch.zeros(2, 3)), torch.tensor([[1.0, 0, 0, 0], [1.0, 0, 0, 0]]))
    v = torch.tensor([[0.0, 0.0, math.tan(0.4)]])
    assert torch.allclose(quat_from_vector(v)[0], q, atol=1e-6)


def test_extra_joint_transforms_rotate_about_the_joint_then_follow_the_parent(device):
    extra, poses, _ = _extra_joints(device)
    pose = poses[1]
    rotations = torch.stack([_axis_quaternion([1.0, 2.0, 0.5], 0.9), _axis_quaternion([0.0, 1.0, 0.0], -0.4)])
    transforms = extra.transforms(pose, rotations.to(device))
    centres = extra.positions().detach()
    for e, parent in enumerate(extra.parents.tolist()):
        rotation = quat_to_matrix(rotations[e]).to(device)
        local = torch.eye(4, device=device)
        local[:3, :3] = rotation
        local[:3, 3] = centres[e] - rotation @ centres[e]
        assert torch.allclose(transforms[e], pose[parent] @ local, atol=1e-5)
        # the joint itself goes where its parent takes it
        moved = transforms[e, :3, :3] @ centres[e] + transforms[e, :3, 3]
        assert torch.allclose(moved, pose[parent, :3, :3] @ centres[e] + pose[parent, :3, 3], atol=1e-5)
    identity = torch.tensor([[1.0, 0.0, 0.0, 0.0]] * 2, device=device)
    assert torch.allclose(extra.transforms(pose, identity), pose[extra.parents], atol=1e-6)
    with pytest.raises(ValueError, match="rotations must have shape"):
        extra.transforms(pose, identity[:1])


def test_training_instants_replay_their_rotations_and_other_poses_rest(device):
    extra, poses, generator = _extra_joints(device)
    for frame in (0, 3):
        expected = extra.frame_rotations(torch.tensor(frame, device=device))
        assert torch.allclose(extra.rotations_for_pose(poses[frame]), expected)
        assert (expected[:, 1:].abs().max() > 0.05)  # not the identity
    assert not torch.allclose(extra.frame_rotations(torch.tensor(0, device=device)),
                              extra.frame_rotations(torch.tensor(3, device=device)))
    novel = _random_rigid(3, generator).to(device)
    assert torch.equal(extra.rotations_for_pose(novel),
                       torch.tensor([[1.0, 0.0, 0.0, 0.0]] * 2, device=device))


def test_rotation_gradient_through_lbs_matches_finite_differences(device):
    extra, poses, generator = _extra_joints(device)
    points = torch.randn(40, 3, generator=generator).to(device)
    weights = torch.softmax(torch.randn(40, 5, generator=generator), dim=-1).to(device)
    target = torch.randn(40, 3, generator=generator).to(device)
    vector = torch.tensor([[0.2, -0.3, 0.1], [0.05, 0.4, -0.2]], device=device)

    def loss(v):
        bones = torch.cat([poses[2], extra.transforms(poses[2], quat_from_vector(v))])
        posed, _ = ops.lbs(points, weights, bones)
        return ((posed - target) ** 2).sum()

    v = vector.clone().requires_grad_(True)
    loss(v).backward()
    numeric = torch.zeros_like(vector)
    step = 1e-2
    with torch.no_grad():
        for index in np.ndindex(*vector.shape):
            plus, minus = vector.clone(), vector.clone()
            plus[index] += step
            minus[index] -= step
            numeric[index] = (loss(plus) - loss(minus)) / (2 * step)
    assert torch.allclose(v.grad, numeric, rtol=2e-2, atol=2e-2 * float(numeric.abs().max()))
    # and the rotation decoder receives gradient from a posed loss
    bones = torch.cat([poses[2], extra.transforms(poses[2])])
    ((ops.lbs(points, weights, bones)[0] - target) ** 2).sum().backward()
    assert extra.rotation_mlp[-1].weight.grad.abs().max() > 0
    assert extra.position_mlp[-1].weight.grad.abs().max() > 0


def test_extra_joint_errors():
    poses = torch.eye(4).repeat(3, 2, 1, 1)
    with pytest.raises(ValueError, match="parents must index"):
        ExtraJoints(torch.tensor([2]), torch.zeros(1, 3), poses, torch.arange(3.0), extent=1.0)
    with pytest.raises(ValueError, match="base_positions"):
        ExtraJoints(torch.tensor([0]), torch.zeros(2, 3), poses, torch.arange(3.0), extent=1.0)
    with pytest.raises(ValueError, match="frame_times"):
        ExtraJoints(torch.tensor([0]), torch.zeros(1, 3), poses, torch.arange(4.0), extent=1.0)
    with pytest.raises(ValueError, match="at least one"):
        ExtraJoints(torch.zeros(0, dtype=torch.long), torch.zeros(0, 3), poses, torch.arange(3.0), extent=1.0)


# ----------------------------------------------------------------------------- field, avatar, files
@pytest.fixture(scope="module")
def demo_skeleton():
    return data.load_video_folder(data.demo_subject_path() / "train", max_frames=4)


def _avatar(video, device):
    return small_avatar(video.skeleton, seed=6, per_bone=6, cells=10, distill_steps=20).to(device)


def _grow(avatar, video, parents, device):
    bones = torch.as_tensor(video.bone_transforms, dtype=torch.float32, device=device)
    heads = torch.as_tensor(video.skeleton.heads, device=device)
    parents = torch.as_tensor(parents, device=device)
    extra = ExtraJoints(parents, heads[parents], bones, torch.arange(bones.shape[0], dtype=torch.float32) / 30,
                        extent=1.0, hidden_position=16, hidden_rotation=16, layers=2).to(device)
    avatar.field.add_joints(parents)
    avatar.add_part(extra)
    return extra


def test_growing_changes_no_render_and_groups_keep_the_bone_loss(demo_skeleton, device):
    video = demo_skeleton
    avatar = _avatar(video, device)
    bones = torch.as_tensor(video.bone_transforms[2], dtype=torch.float32, device=device)
    camera = video.cameras[2]
    heads = torch.as_tensor(video.skeleton.heads, device=device)
    tails = torch.as_tensor(video.skeleton.tails, device=device)
    from warpavatar.model.skinning_field import bone_sample_points
    samples, sample_bones = bone_sample_points(heads, tails, torch.as_tensor(video.skeleton.parents, device=device))
    with torch.no_grad():
        before, _, _ = avatar.render(camera, bones)
        weights_before = avatar.field.weights(avatar.gaussians.means)
        bone_before = avatar.field.bone_loss(samples, sample_bones)
    _grow(avatar, video, [3, 3, 7], device)
    assert avatar.field.joint_count == avatar.joint_count + 3
    identity = torch.tensor([[1.0, 0.0, 0.0, 0.0]] * 3, device=device)
    with torch.no_grad():
        weights_after = avatar.field.weights(avatar.gaussians.means)
        grouped = weights_after @ avatar.skinning_groups()
        assert torch.allclose(grouped, weights_before, atol=1e-5)
        # each child shares its parent's weight: parent 3 with two children keeps a third of it
        assert torch.allclose(weights_after[:, 3], weights_before[:, 3] / 3, atol=1e-5)
        assert torch.allclose(weights_after[:, -1], weights_before[:, 7] / 2, atol=1e-5)
        after, _, _ = avatar.render(camera, bones, inputs={"joint_growth": identity})
        bone_after = avatar.field.bone_loss(samples, sample_bones, groups=avatar.skinning_groups())
    assert (before - after).abs().max() < 1e-4
    assert abs(float(bone_after) - float(bone_before)) < 1e-5
    # a rotated grown joint moves the Gaussians it has weight on
    turn = torch.stack([_axis_quaternion([0.0, 1.0, 0.0], 0.8)] * 3).to(device)
    with torch.no_grad():
        turned, _, _ = avatar.render(camera, bones, inputs={"joint_growth": turn})
    assert (turned - before).abs().max() > 0.05


def test_grown_avatar_file_round_trip_and_rig(demo_skeleton, device, tmp_path):
    video = demo_skeleton
    avatar = _avatar(video, device)
    extra = _grow(avatar, video, [5, 1], device)
    with torch.no_grad():
        extra.rotation_mlp[-1].bias.copy_(torch.tensor([0.3, -0.2, 0.4], device=device))
    avatar.save(tmp_path / "avatar.pt")
    loaded = Avatar.load(tmp_path, device=device)
    assert loaded.part("joint_growth") is not None and loaded.part("joint_growth").count == 2
    assert loaded.grown_joint_count == 2
    for frame in (1, 3):
        bones = torch.as_tensor(video.bone_transforms[frame], dtype=torch.float32, device=device)
        with torch.no_grad():
            original, _, _ = avatar.render(video.cameras[frame], bones)
            reloaded, _, _ = loaded.render(video.cameras[frame], bones)
            assert torch.equal(avatar.pose_bones(bones), loaded.pose_bones(bones))
        assert (original - reloaded).abs().max() < 1e-5
    rig = loaded.rig()
    names = video.skeleton.names
    assert rig.names[-2:] == [f"grown_{names[5]}_0", f"grown_{names[1]}_1"]
    assert rig.parents[-2:].tolist() == [5, 1]
    assert np.allclose(rig.heads[-2:], extra.positions().detach().cpu().numpy(), atol=1e-6)
    plain = _avatar(video, device)
    with pytest.raises(ValueError, match="inputs for parts this avatar does not have: \\['joint_growth'\\]"):
        plain.pose_bones(torch.eye(4, device=device).repeat(plain.joint_count, 1, 1),
                         inputs={"joint_growth": torch.ones(1, 4, device=device)})


def test_grown_skeleton_exports_to_usd(demo_skeleton, tmp_path, capsys):
    pytest.importorskip("pxr")
    from warpavatar.cli import animate
    from warpavatar.io.usd import read_gaussian_usd

    video = demo_skeleton
    avatar = _avatar(video, "cpu")
    _grow(avatar, video, [4], "cpu")
    with torch.no_grad():
        avatar.part("joint_growth").rotation_mlp[-1].bias.copy_(torch.tensor([0.0, 0.5, 0.0]))
    avatar.save(tmp_path / "avatar.pt")
    output = tmp_path / "motion.usdc"
    assert animate.main([str(tmp_path), "--motion", str(data.demo_subject_path() / "train"), "--frames", "0:3",
                         "-o", str(output), "--skeleton", "--device", "cpu", "--no-progress"]) == 0
    result = read_gaussian_usd(output)
    assert result["joint_paths"][-1].endswith(f"grown_{video.skeleton.names[4]}_0")
    assert len(result["joint_paths"]) == video.skeleton.joint_count + 1
    # the grown joint's animation reads back as the avatar's transform of each (training-instant) pose
    for t in range(3):
        bones = torch.as_tensor(video.bone_transforms[t], dtype=torch.float32)
        with torch.no_grad():
            expected = avatar.pose_bones(bones).numpy()
        assert np.abs(result["joint_transforms"][t] - expected).max() < 1e-4
        assert np.abs(expected[-1] - expected[4]).max() > 1e-2  # it does turn away from its parent

    # explicit rotations from a file animate the grown joint instead (animate and render take the same file)
    chosen = np.stack([_axis_quaternion([1.0, 0.0, 0.0], 0.3 * (t + 1)).numpy() for t in range(3)])[:, None]
    np.save(tmp_path / "grown.npy", 2.0 * chosen)  # not unit length: normalized on reading
    explicit = tmp_path / "explicit.usdc"
    assert animate.main([str(tmp_path), "--motion", str(data.demo_subject_path() / "train"), "--frames", "0:3",
                         "-o", str(explicit), "--skeleton", "--device", "cpu", "--no-progress",
                         "--grown-rotations", str(tmp_path / "grown.npy")]) == 0
    result = read_gaussian_usd(explicit)
    for t in range(3):
        bones = torch.as_tensor(video.bone_transforms[t], dtype=torch.float32)
        with torch.no_grad():
            explicit = {"joint_growth": torch.as_tensor(chosen[t])}
            expected = avatar.pose_bones(bones, inputs=explicit).numpy()
            posed = avatar.pose(bones, inputs=explicit)["means"].numpy()
        assert np.abs(result["joint_transforms"][t] - expected).max() < 1e-4
        assert np.abs(result["positions"][t] - posed).max() < 1e-5
    np.save(tmp_path / "short.npy", chosen[:2])
    # the CLI reports the file and the expected shape (no traceback) and writes nothing
    assert animate.main([str(tmp_path), "--motion", str(data.demo_subject_path() / "train"), "--frames", "0:3",
                         "-o", str(tmp_path / "bad.usdc"), "--device", "cpu", "--no-progress",
                         "--grown-rotations", str(tmp_path / "short.npy")]) != 0
    assert "short.npy: rotations must have shape [3, 1, 4]" in capsys.readouterr().err
    assert not (tmp_path / "bad.usdc").exists()


def test_grown_rotation_files_are_checked(tmp_path):
    from warpavatar.io.animation import read_grown_rotations

    good = np.tile(np.array([0.0, 0.0, 2.0, 0.0]), (5, 2, 1))
    np.savez(tmp_path / "good.npz", rotations=good)
    loaded = read_grown_rotations(tmp_path / "good.npz", frame_count=5, joint_count=2)
    assert np.allclose(loaded, good / 2.0)
    np.savez(tmp_path / "other.npz", quats=good)
    with pytest.raises(ValueError, match="other.npz.*no 'rotations' array"):
        read_grown_rotations(tmp_path / "other.npz", frame_count=5, joint_count=2)
    with pytest.raises(ValueError, match=r"shape \[4, 2, 4\]"):
        read_grown_rotations(tmp_path / "good.npz", frame_count=4, joint_count=2)
    bad = good.copy()
    bad[1, 0] = 0.0
    np.save(tmp_path / "zero.npy", bad)
    with pytest.raises(ValueError, match="zero.npy.*non-zero"):
        read_grown_rotations(tmp_path / "zero.npy", frame_count=5, joint_count=2)
    with pytest.raises(ValueError, match="no grown joints"):
        read_grown_rotations(tmp_path / "good.npz", frame_count=5, joint_count=0)
    (tmp_path / "junk.npy").write_text("not an array")
    with pytest.raises(ValueError, match="junk.npy: not a usable"):
        read_grown_rotations(tmp_path / "junk.npy", frame_count=5, joint_count=2)


def test_config_rejects_unsupported_combinations():
    with pytest.raises(ValueError, match="grow-joints"):
        preset(grow_joints=True, dynamics=True)
    with pytest.raises(ValueError, match="grow-joints"):
        preset(grow_joints=True, backward_mapping=True)
    with pytest.raises(ValueError, match="grow_threshold"):
        preset(grow_joints=True, grow_threshold=0.0)


def test_misspelt_grow_parents_fail_before_the_fit(tmp_path):
    from warpavatar.fit import Trainer

    video = data.load_video_folder(data.demo_subject_path() / "train", max_frames=4, scale=0.25)
    config = preset(grow_joints=True, grow_parents="Hips,NotAJoint", init_carve=False, init_points_per_bone=5,
                    grid_cells=8, grid_min_cells=4, field_hidden=16, field_layers=1)
    with pytest.raises(ValueError, match="does not have: NotAJoint "):
        Trainer(video, config, tmp_path / "fit")


def test_history_offsets_are_what_the_frame_code_adds(device):
    """The 'history' growth criterion reads the part of the pose correction that the frame codes add."""
    from warpavatar.extensions.pose_correction import PoseCorrection

    generator = torch.Generator().manual_seed(8)
    parents = torch.tensor([-1, 0, 1])
    poses = torch.stack([_random_rigid(3, generator) for _ in range(4)]).to(device)
    correction = PoseCorrection(torch.zeros(3), torch.ones(3), parents, hidden=16, layers=2, frame_count=4,
                                code_width=5).to(device)
    correction.set_frame_poses(poses)
    means = torch.rand(30, 3, generator=generator).to(device)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]], device=device).repeat(30, 1)
    scales = torch.full((30, 3), 0.02, device=device)
    with torch.no_grad():
        correction.head.weight.copy_(torch.randn(correction.head.weight.shape, generator=generator) * 0.3)
        correction.frame_codes.copy_(torch.randn(4, 5, generator=generator))
        offsets = correction.history_offsets(means, 2)
        corrected, _, _ = correction(means, quats, scales, poses[2])
        codes = correction.frame_codes.clone()
        correction.frame_codes.zero_()
        pose_only, _, _ = correction(means, quats, scales, poses[2])
        correction.frame_codes.copy_(codes)
    assert torch.allclose(offsets, corrected - pose_only, atol=1e-6)
    assert float(offsets.abs().max()) > 1e-3
    plain = PoseCorrection(torch.zeros(3), torch.ones(3), parents, hidden=16, layers=2).to(device)
    assert torch.equal(plain.history_offsets(means, 0), torch.zeros_like(means))


def test_history_criterion_needs_the_frame_codes():
    with pytest.raises(ValueError, match="grow-criterion history"):
        preset(grow_joints=True, grow_criterion="history", frame_codes=False, grow_at=3000)
    with pytest.raises(ValueError, match="grow-criterion history"):
        preset(grow_joints=True, grow_criterion="history", grow_at=1000, gaussian_only_steps=1500)
    with pytest.raises(ValueError, match="grow-criterion history"):
        preset(grow_joints=True, grow_criterion="history", grow_at=3000, pose_correction=False)
    with pytest.raises(ValueError, match="grow_criterion must be"):
        preset(grow_joints=True, grow_criterion="curvature")
    preset(grow_joints=True, grow_criterion="history", frame_codes=True, grow_at=3000)  # the combination that works
