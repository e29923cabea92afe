"""warpavatar-animate and warpavatar-render on a small avatar built from the demo skeleton."""

import json

import cv2
import numpy as np
import pytest
import torch

pytest.importorskip("pxr")  # usd-core is a dependency; skip cleanly where it is absent (the GPU machine)

from conftest import small_avatar
from warpavatar import data
from warpavatar.model import Avatar
from warpavatar.cli import animate, render
from warpavatar.io.usd import read_gaussian_usd


@pytest.fixture(scope="module")
def avatar_dir(tmp_path_factory):
    """An avatar with Gaussians scattered around the demo skeleton's bones and a field distilled briefly."""
    skeleton = data.load_video_folder(data.demo_subject_path() / "train", max_frames=2).skeleton
    avatar = small_avatar(skeleton, seed=3, per_bone=8, cells=12, distill_steps=30, random_frames=True)
    folder = tmp_path_factory.mktemp("avatar")
    avatar.save(folder / "avatar.pt")
    return folder


def _expected_positions(avatar_dir, bone_transforms):
    avatar = Avatar.load(avatar_dir)
    with torch.no_grad():
        return [avatar.pose(torch.as_tensor(b, dtype=torch.float32))["means"].numpy() for b in bone_transforms]


@pytest.mark.parametrize("layout", ["particlefield", "points"])
def test_animate_video_folder_motion_reads_back(avatar_dir, tmp_path, layout):
    motion_folder = data.demo_subject_path() / "novel_pose" / "dance_cam000"
    output = tmp_path / f"anim_{layout}.usdc"
    code = animate.main([str(avatar_dir), "--motion", str(motion_folder), "-o", str(output), "--layout", layout,
                         "--frames", "2:6", "--no-progress", "--device", "cpu"])
    assert code == 0 and output.is_file()
    assert not list(tmp_path.glob("*.tmp*"))
    bones = data.load_video_folder(motion_folder).bone_transforms[2:6]
    expected = _expected_positions(avatar_dir, bones)
    usd = read_gaussian_usd(output)
    assert list(usd["time_codes"]) == [0, 3, 6, 9]  # the folder keeps every 3rd frame id: 3 time codes apart
    for t, reference in enumerate(expected):
        np.testing.assert_allclose(usd["positions"][t], reference, atol=1e-5)


def test_animate_bvh_subset_drives_mapped_joints(avatar_dir, tmp_path):
    skeleton = Avatar.load(avatar_dir).skeleton
    root = skeleton.names[0]
    child = skeleton.names[int(np.nonzero(skeleton.parents == 0)[0][0])]
    bvh = tmp_path / "motion.bvh"
    bvh.write_text(
        "HIERARCHY\nROOT {r}\n{{\n OFFSET 0 0 0\n CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation "
        "Yrotation\n JOINT {c}\n {{\n  OFFSET 0 10 0\n  CHANNELS 3 Zrotation Xrotation Yrotation\n  End Site\n  {{\n"
        "   OFFSET 0 10 0\n  }}\n }}\n}}\nMOTION\nFrames: 3\nFrame Time: 0.0333333\n"
        "0 0 0 0 0 0 0 0 0\n0 0 0 0 0 0 30 0 0\n0 0 0 0 0 0 60 0 0\n".format(r=root, c=child))
    name_map = tmp_path / "map.json"
    name_map.write_text(json.dumps({root: root, child: child}))
    output = tmp_path / "bvh.usdc"
    code = animate.main([str(avatar_dir), "--motion", str(bvh), "--name-map", str(name_map), "-o", str(output),
                         "--no-progress", "--device", "cpu"])
    assert code == 0
    usd = read_gaussian_usd(output)
    frames = usd["positions"]
    assert frames.shape[0] == 3
    # the rest frame leaves the Gaussians where they are; the child's rotation then moves some of them
    np.testing.assert_allclose(frames[0], Avatar.load(avatar_dir).gaussians.means.detach().numpy(), atol=1e-4)
    assert np.abs(frames[2] - frames[0]).max() > 1e-3


def test_animate_bad_motion_is_a_clear_error(avatar_dir, tmp_path, capsys):
    bad = tmp_path / "bad.npz"
    np.savez(bad, bone_transforms=np.tile(np.eye(4, dtype=np.float32), (3, 5, 1, 1)))
    code = animate.main([str(avatar_dir), "--motion", str(bad), "-o", str(tmp_path / "x.usdc"), "--no-progress"])
    assert code == 2
    message = capsys.readouterr().err
    assert "bad.npz" in message and "joint" in message
    assert not (tmp_path / "x.usdc").exists()


def test_render_mp4_and_frames(avatar_dir, tmp_path):
    motion_folder = data.demo_subject_path() / "novel_pose" / "dance_cam000"
    video = tmp_path / "orbit.mp4"
    assert render.main([str(avatar_dir), "--motion", str(motion_folder), "-o", str(video), "--orbit", "--size", "64",
                        "--frames", "0:5", "--no-progress", "--device", "cpu"]) == 0
    capture = cv2.VideoCapture(str(video))
    # the folder keeps every k-th frame of its clock: the video plays its rows at fps / k (its captured speed)
    motion = data.load_video_folder(motion_folder)
    step = int(motion.frame_ids[1] - motion.frame_ids[0])
    assert step > 1 and capture.get(cv2.CAP_PROP_FPS) == pytest.approx(motion.fps / step, rel=1e-3)
    count = 0
    while capture.read()[0]:
        count += 1
    assert count == 5
    frames = tmp_path / "frames"
    assert render.main([str(avatar_dir), "--motion", str(motion_folder), "-o", str(frames), "--frames", "0:3",
                        "--no-progress", "--device", "cpu"]) == 0
    images = sorted(frames.glob("*.png"))
    assert len(images) == 3
    first = cv2.imread(str(images[0]))
    assert first.shape[:2] == (128, 128) and first.max() > 0  # the motion folder's own camera, something drawn
