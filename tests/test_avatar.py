"""Avatar pieces that the end-to-end fit does not pin down: canonical-frame SH colours and frame codes."""

import math

import torch

from warpavatar.geometry import quat_rotate
from warpavatar.model import Avatar, PosedGaussians
from warpavatar.extensions.pose_correction import PoseCorrection, relative_rotations_6d


def _random_unit_quats(count, generator):
    q = torch.randn(count, 4, generator=generator)
    return q / q.norm(dim=-1, keepdim=True)


def _quat_multiply(a, b):
    w1, v1 = a[:, :1], a[:, 1:]
    w2, v2 = b[:, :1], b[:, 1:]
    return torch.cat([w1 * w2 - (v1 * v2).sum(-1, keepdim=True), w1 * v2 + w2 * v1 + torch.cross(v1, v2, dim=-1)], -1)


def _rotation_z(angle):
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def test_quat_rotate_matches_matrix():
    generator = torch.Generator().manual_seed(1)
    angle = 0.7
    q = torch.tensor([[math.cos(angle / 2), 0.0, 0.0, math.sin(angle / 2)]]).repeat(5, 1)
    v = torch.randn(5, 3, generator=generator)
    assert torch.allclose(quat_rotate(q, v), v @ _rotation_z(angle).T, atol=1e-6)
    assert torch.allclose(quat_rotate(q, quat_rotate(q, v), inverse=True), v, atol=1e-6)


def test_view_colors_follow_the_body_not_the_world():
    """Turning the subject and the camera together by the same rotation leaves every colour unchanged."""
    generator = torch.Generator().manual_seed(2)
    count = 50
    canonical = _random_unit_quats(count, generator)
    means = torch.randn(count, 3, generator=generator)
    colors = torch.randn(count, 16, 3, generator=generator) * 0.3
    world_to_camera = torch.eye(4)
    world_to_camera[:3, 3] = torch.tensor([0.1, -0.2, 4.0])

    def posed_colors(angle):
        rotation = _rotation_z(angle)
        turn = torch.tensor([[math.cos(angle / 2), 0.0, 0.0, math.sin(angle / 2)]]).repeat(count, 1)
        posed = PosedGaussians(means=means @ rotation.T, quats=_quat_multiply(turn, canonical), colors=colors,
                               sh_degree=3, canonical_quats=canonical)
        camera = world_to_camera.clone()
        camera[:3, :3] = world_to_camera[:3, :3] @ rotation.T  # the camera turns with the subject
        return Avatar.view_colors(posed, camera)

    still, turned = posed_colors(0.0), posed_colors(1.1)
    assert torch.allclose(still, turned, atol=1e-5)
    # while a world-frame evaluation would change: the camera alone turning does change colours
    posed = PosedGaussians(means=means, quats=canonical, colors=colors, sh_degree=3, canonical_quats=canonical)
    camera = world_to_camera.clone()
    camera[:3, :3] = _rotation_z(1.1)
    assert not torch.allclose(Avatar.view_colors(posed, camera), still, atol=1e-3)


def test_frame_code_is_used_only_for_training_poses():
    generator = torch.Generator().manual_seed(3)
    joint_count, frame_count = 4, 6
    parents = torch.tensor([-1, 0, 1, 1])
    poses = torch.eye(4).repeat(frame_count, joint_count, 1, 1)
    for t in range(frame_count):
        for j in range(joint_count):
            poses[t, j, :3, :3] = _rotation_z(0.1 * t + 0.05 * j)
            poses[t, j, :3, 3] = torch.randn(3, generator=generator)
    correction = PoseCorrection(torch.zeros(3) - 1, torch.ones(3), parents, hidden=8, layers=1,
                                frame_count=frame_count, code_width=5)
    with torch.no_grad():
        correction.frame_codes.normal_(generator=generator)
    correction.set_frame_poses(poses)
    for t in range(frame_count):
        assert torch.equal(correction.frame_code(poses[t]), correction.frame_codes[t])
    other = poses[2].clone()
    other[1, :3, 3] += 0.01
    assert torch.equal(correction.frame_code(other), torch.zeros(5))


def test_pose_correction_regularizer_keeps_the_training_pose_gradient():
    """A pose without gradients in the middle of a step (the backward mapping's refresh) must not replace the
    outputs the regularizer differentiates."""
    generator = torch.Generator().manual_seed(4)
    parents = torch.tensor([-1, 0, 1])
    correction = PoseCorrection(torch.zeros(3) - 1, torch.ones(3), parents, hidden=8, layers=1)
    with torch.no_grad():
        correction.head.weight.normal_(generator=generator)
    means = torch.rand(20, 3, generator=generator)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(20, 1)
    scales = torch.full((20, 3), 0.05)
    pose = torch.eye(4).repeat(3, 1, 1)
    pose[1, :3, :3] = _rotation_z(0.4)
    correction(means, quats, scales, pose)
    with torch.no_grad():
        correction(means, quats, scales, torch.eye(4).repeat(3, 1, 1))
    regularizer = correction.regularization()
    assert regularizer.requires_grad and float(regularizer.detach()) > 0
    regularizer.backward()
    assert float(correction.head.weight.grad.abs().max()) > 0


def test_relative_rotations_ignore_global_heading():
    generator = torch.Generator().manual_seed(4)
    parents = torch.tensor([-1, 0, 1])
    bones = torch.eye(4).repeat(3, 1, 1)
    for j in range(3):
        bones[j, :3, :3] = _rotation_z(0.3 * (j + 1))
        bones[j, :3, 3] = torch.randn(3, generator=generator)
    turned = bones.clone()
    turned[:, :3, :3] = _rotation_z(0.9) @ bones[:, :3, :3]
    assert torch.allclose(relative_rotations_6d(bones, parents), relative_rotations_6d(turned, parents), atol=1e-6)
    assert relative_rotations_6d(bones, parents).abs().max() > 0.1


def test_world_shading_ignores_the_rendering_camera():
    """With a shading origin, colours do not depend on where the rendering camera is."""
    generator = torch.Generator().manual_seed(3)
    count = 40
    quats = torch.randn(count, 4, generator=generator)
    quats = quats / quats.norm(dim=-1, keepdim=True)
    posed = PosedGaussians(means=torch.randn(count, 3, generator=generator), quats=quats,
                           colors=torch.randn(count, 4, 3, generator=generator) * 0.3, sh_degree=1,
                           canonical_quats=quats)
    origin = torch.tensor([0.0, 0.0, -4.0])
    first, second = torch.eye(4), torch.eye(4)
    first[:3, 3] = torch.tensor([0.0, 0.0, 4.0])
    angle = 1.3
    second[:3, :3] = torch.tensor([[math.cos(angle), 0.0, math.sin(angle)], [0.0, 1.0, 0.0],
                                   [-math.sin(angle), 0.0, math.cos(angle)]])
    second[:3, 3] = torch.tensor([0.5, 0.0, 4.0])
    a = Avatar.view_colors(posed, first, origin=origin)
    b = Avatar.view_colors(posed, second, origin=origin)
    assert torch.equal(a, b)
    # and equals the view-dependent colour for a camera whose centre is the origin
    assert torch.allclose(a, Avatar.view_colors(posed, first), atol=1e-6)
    assert not torch.allclose(a, Avatar.view_colors(posed, second), atol=1e-3)
