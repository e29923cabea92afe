"""research/pose_error.py: pose errors against exact poses, split along and across each frame's camera axis."""

import math

import cv2
import numpy as np
import pytest
import torch

from research import pose_error
from warpavatar import data
from warpavatar.model.kinematics import ancestor_jumps, corrected_transforms

pytestmark = pytest.mark.research


@pytest.fixture(scope="module")
def tool():
    return pose_error


@pytest.fixture(scope="module")
def demo():
    return data.load_video_folder(data.demo_subject_path() / "train", max_frames=6)


def test_a_rigid_shift_is_split_along_and_across_the_camera_axis(tool, demo):
    exact = np.asarray(demo.bone_transforms, dtype=np.float64)
    shift = np.array([0.03, -0.01, 0.02])
    moved = exact.copy()
    moved[..., :3, 3] += shift  # every pivot moves by the same vector; no rotation changes
    errors = tool.pose_errors(exact, moved, demo.skeleton.heads, demo.skeleton.parents, demo.cameras)
    intrinsics = np.stack([np.asarray(camera.K) for camera in demo.cameras])
    world_to_camera = np.stack([np.asarray(camera.world_to_camera) for camera in demo.cameras])
    axes = world_to_camera[:, 2, :3]  # each frame's optical axis in the world
    along = np.abs(axes @ shift)
    assert np.allclose(errors["pivots"], np.linalg.norm(shift), atol=1e-6)
    assert np.allclose(errors["along_axis"], along[:, None], atol=1e-6)
    assert np.allclose(errors["across"], np.sqrt(shift @ shift - along ** 2)[:, None], atol=1e-6)
    assert np.allclose(errors["bias"], np.linalg.norm(shift), atol=1e-6)
    assert np.abs(errors["rotation_deg"]).max() < 1e-4
    # pixels: the distance between the pivots' projections, as OpenCV projects them
    heads = demo.skeleton.heads
    for t in range(exact.shape[0]):
        rvec = cv2.Rodrigues(world_to_camera[t, :3, :3])[0]
        projected = [cv2.projectPoints(np.einsum("jab,jb->ja", poses[t, :, :3, :3], heads) + poses[t, :, :3, 3],
                                       rvec, world_to_camera[t, :3, 3], intrinsics[t], None)[0][:, 0]
                     for poses in (exact, moved)]
        assert np.allclose(errors["pixels"][t], np.linalg.norm(projected[1] - projected[0], axis=-1), rtol=1e-6)


def test_a_turned_joint_shows_its_angle_and_moves_its_children_only(tool, demo):
    exact = torch.as_tensor(np.asarray(demo.bone_transforms), dtype=torch.float64)
    parents = np.asarray(demo.skeleton.parents)
    joint = int(np.flatnonzero(np.bincount(parents[parents >= 0], minlength=len(parents)) > 0)[1])  # has children
    rotation = torch.zeros(exact.shape[0], exact.shape[1], 3, dtype=torch.float64)
    rotation[:, joint] = torch.tensor([0.0, 0.0, math.radians(7.0)])
    heads = torch.as_tensor(demo.skeleton.heads, dtype=torch.float64)
    turned = corrected_transforms(exact, heads, ancestor_jumps(parents.tolist()), rotation,
                                  torch.zeros(exact.shape[0], 3, dtype=torch.float64))
    errors = tool.pose_errors(exact.numpy(), turned.numpy(), demo.skeleton.heads, parents, demo.cameras)
    assert np.allclose(errors["rotation_deg"][:, joint], 7.0, atol=1e-3)
    others = np.delete(errors["rotation_deg"], joint, axis=1)
    assert others.max() < 1e-2  # the children follow: their rotations relative to their parents are unchanged
    children = np.flatnonzero(parents == joint)
    assert (errors["pivots"][:, children] > 1e-4).all()  # they move about the turned joint's pivot
    assert errors["pivots"][:, joint].max() < 1e-6  # which stays put


def test_command_reports_files_and_folders_and_rejects_bad_ones(tool, demo, tmp_path, capsys):
    exact = np.asarray(demo.bone_transforms)
    moved = exact.copy()
    moved[..., :3, 3] += np.array([0.0, 0.0, 0.05], dtype=np.float32)
    fit = tmp_path / "fit"
    fit.mkdir()
    data.write_poses(fit / "poses_refined.npz", moved, demo.frame_ids)
    folder = data.demo_subject_path()
    assert tool.main([str(folder), str(fit), "--per-joint", "2"]) == 0
    lines = [line for line in capsys.readouterr().out.splitlines() if line.startswith("| ")]
    assert len(lines) == 1 + 1 + 2  # header, the file's row, its two worst joints
    assert lines[1].split(" | ")[1] == str(demo.frame_ids.shape[0])  # the frames it shares with the folder
    assert float(lines[1].split(" | ")[2]) == pytest.approx(50.0, abs=1e-3)  # mm
    wrong = tmp_path / "wrong.npz"
    data.write_poses(wrong, moved[:, :3], demo.frame_ids)
    assert tool.main([str(folder), str(wrong)]) == 2
    message = capsys.readouterr().err.strip()
    assert message.startswith("pose_error: ") and "joint count mismatch" in message and "\n" not in message
    assert tool.main([str(folder), str(tmp_path)]) == 2
    assert "holds neither poses_refined.npz" in capsys.readouterr().err
    late = tmp_path / "late.npz"
    data.write_poses(late, moved, demo.frame_ids + 100000)
    assert tool.main([str(folder), str(late)]) == 2
    assert "shares no frame id" in capsys.readouterr().err
