"""Plausibility checks on load (docs/FORMAT.md, "Checks on load"): inputs that are valid but absurd. Each test
breaks exactly one rule in a copy of four frames of the demo subject and checks the exact message, which names the
file; warnings are checked the same way."""

import copy
import json
import shutil
import warnings

import cv2
import numpy as np
import pytest

from conftest import small_avatar
from warpavatar import data
from warpavatar.cli import animate, render
from warpavatar.data import VideoFolderError
from warpavatar.data.checks import VideoFolderWarning
from warpavatar.io.animation import read_cameras_json
from warpavatar.io.motion import MotionError, load_motion

FRAMES = 4
IDS = "000000, 000002, 000004, 000006"  # the first four frame ids of the demo's train folder


@pytest.fixture(scope="module")
def demo_copy(tmp_path_factory):
    """Four frames of the demo's training folder (128x128, 41 joints, masks, a fixed camera), written anew."""
    video = data.load_video_folder(data.demo_subject_path() / "train", max_frames=FRAMES)
    assert ", ".join(f"{i:06d}" for i in video.frame_ids) == IDS
    return data.write_video_folder(video, tmp_path_factory.mktemp("plausibility") / "video")


@pytest.fixture
def folder(demo_copy, tmp_path):
    return shutil.copytree(demo_copy, tmp_path / "video")


def _edit_json(path, edit):
    document = json.loads(path.read_text())
    edit(document)
    path.write_text(json.dumps(document))


def _edit_poses(path, edit):
    with np.load(path) as archive:
        arrays = dict(archive)
    edit(arrays)
    np.savez(path, **arrays)


def _load_error(folder) -> str:
    with pytest.raises(VideoFolderError) as caught:
        data.load_video_folder(folder)
    return str(caught.value)


def _load_warnings(folder) -> list[str]:
    """Load the folder (it must load) and return the VideoFolderWarnings it gave."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        video = data.load_video_folder(folder)
    assert video.frame_count == FRAMES
    return [str(w.message) for w in caught if issubclass(w.category, VideoFolderWarning)]


def _turned_round(matrix):
    """The camera turned half a turn about its own vertical axis: every depth changes sign."""
    flip = np.diag([-1.0, 1.0, -1.0, 1.0])
    return (flip @ np.asarray(matrix)).tolist()


def _per_frame(folder, edit_row):
    """Give cameras.json one camera per frame, ``edit_row(index, camera)`` changing some of them."""
    def edit(document):
        cameras = [copy.deepcopy({"K": document["K"], "world_to_camera": document["world_to_camera"]})
                   for _ in range(FRAMES)]
        for index, camera in enumerate(cameras):
            edit_row(index, camera)
        document["frames"] = cameras
    _edit_json(folder / "cameras.json", edit)


# ------------------------------------------------------------------------------------------------ the camera
def test_the_demo_copy_loads_without_warnings(folder):
    assert _load_warnings(folder) == []


def test_a_camera_with_the_subject_behind_it_is_refused(folder):
    _edit_json(folder / "cameras.json", lambda d: d.update(world_to_camera=_turned_round(d["world_to_camera"])))
    assert _load_error(folder) == (
        f"{folder / 'cameras.json'}: the subject is behind the camera (most joints at depth <= 0) in 4 of 4 frames "
        f"(frame ids {IDS}): is 'world_to_camera' a camera-to-world matrix, or the camera turned away from the "
        "subject?")


def test_one_frame_with_the_subject_behind_the_camera_is_a_warning(folder):
    _per_frame(folder, lambda index, camera: camera.update(world_to_camera=_turned_round(camera["world_to_camera"]))
               if index == 2 else None)
    assert _load_warnings(folder) == [
        f"{folder / 'cameras.json'}: the subject is behind the camera (most joints at depth <= 0) in 1 of 4 frames "
        "(frame ids 000004); those frames show no subject"]


def test_a_subject_outside_every_view_is_refused(folder):
    def shift(document):
        document["world_to_camera"][0][3] += 100.0  # 100 m to the side of the camera
    _edit_json(folder / "cameras.json", shift)
    assert _load_error(folder) == (
        f"{folder / 'cameras.json'}: the subject projects outside the 128x128 image (no joint inside it) in 4 of 4 "
        f"frames (frame ids {IDS}): check 'K' (focal lengths, cx, cy) and the translation of 'world_to_camera'")


def test_a_subject_outside_the_image_in_some_frames_is_a_warning(folder):
    _per_frame(folder, lambda index, camera: camera["world_to_camera"][1].__setitem__(3, 50.0) if index < 2 else None)
    assert _load_warnings(folder) == [
        f"{folder / 'cameras.json'}: the subject projects outside the 128x128 image (no joint inside it) in 2 of 4 "
        "frames (frame ids 000000, 000002); those frames show no subject"]


@pytest.mark.parametrize("focal,accepted", [(1e30, False), (1e-30, False), (6.39, False), (6401.0, False),
                                            (6.4, True), (640.0, True)])
def test_focal_lengths_must_be_a_sane_multiple_of_the_image_size(folder, focal, accepted):
    _edit_json(folder / "cameras.json", lambda d: d["K"][0].__setitem__(0, focal))
    if accepted:  # 0.05x and 5x the 128 pixels
        assert data.load_video_folder(folder).cameras[0].K[0, 0] == np.float32(focal)
        return
    fy = 190.9557
    assert _load_error(folder) == (
        f"{folder / 'cameras.json'}: the camera 'K' has implausible focal lengths fx={focal:.6g}, fy={fy:.6g} pixels: "
        "they must lie within 0.05 to 50 times the image's larger side (128 pixels), 6.4 to 6400")


# ------------------------------------------------------------------------------------------------ the masks
def _rewrite_masks(folder, convert, suffix=".png"):
    for path in sorted((folder / "masks").glob("*.png")):
        mask = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        path.unlink()
        cv2.imwrite(str(path.with_suffix(suffix)), convert(mask))


@pytest.mark.parametrize("convert", [
    lambda m: (m // 255).astype(np.uint8),           # 0/1
    lambda m: (m // 255).astype(np.uint16),          # 0/1 in a 16-bit file
    lambda m: m.astype(np.uint16) * 257,             # 0/65535
    lambda m: m.astype(np.uint16),                   # 0/255 in a 16-bit file
], ids=["0-1", "0-1 16-bit", "0-65535", "0-255 16-bit"])
def test_binary_masks_read_alike_in_any_scale(folder, convert):
    expected = data.load_video_folder(folder).masks
    assert set(np.unique(expected)) == {0, 255}
    _rewrite_masks(folder, convert)
    assert _load_warnings(folder) == []
    np.testing.assert_array_equal(data.load_video_folder(folder).masks, expected)


def test_a_mask_that_is_not_two_valued_is_thresholded_at_half_scale_with_a_warning(folder):
    path = folder / "masks" / "000002.png"
    ramp = np.tile(np.linspace(0, 255, 128).round().astype(np.uint8), (128, 1))  # one column per value
    cv2.imwrite(str(path), ramp)
    between = np.mean((ramp > 25.5) & (ramp < 229.5))
    assert _load_warnings(folder) == [
        f"{path}: not a two-valued mask: {between:.0%} of its pixels lie between 0 and full scale; read as subject "
        "where at least half of full scale"]
    with pytest.warns(VideoFolderWarning):
        mask = data.load_video_folder(folder).masks[1]
    np.testing.assert_array_equal(mask, np.where(ramp >= 128, 255, 0))


def test_all_empty_masks_are_refused(folder):
    _rewrite_masks(folder, np.zeros_like)
    assert _load_error(folder) == (
        f"{folder / 'masks'}: every one of the 4 masks is empty (no foreground pixel): the subject is 255 in 0/255 "
        "masks, 1 in 0/1 masks, 65535 in 16-bit ones")


def test_empty_masks_in_most_frames_are_refused(folder):
    for name in ("000000", "000002", "000006"):
        cv2.imwrite(str(folder / "masks" / f"{name}.png"), np.zeros((128, 128), np.uint8))
    assert _load_error(folder) == (
        f"{folder / 'masks'}: the masks are empty (no foreground pixel) in 3 of 4 frames (frame ids 000000, 000002, "
        "000006): a fit needs the subject's silhouette in most frames")


def test_an_empty_mask_in_some_frames_is_a_warning_that_counts_them(folder):
    cv2.imwrite(str(folder / "masks" / "000004.png"), np.zeros((128, 128), np.uint8))
    assert _load_warnings(folder) == [
        f"{folder / 'masks'}: the masks are empty (no foreground pixel) in 1 of 4 frames (frame ids 000004); those "
        "frames show no subject"]


# ------------------------------------------------------------------------------------------------ frame ids, fps
@pytest.mark.parametrize("frame_ids,problem", [
    (np.array([0, 2, 4, 2**31], np.int64), "must be integers from 0 to 2147483647 (int32), got 2147483648 at row 3"),
    (np.array([0, 2, 4, 2**32 + 6], np.int64), "must be integers from 0 to 2147483647 (int32), got 4294967302 at "
                                                "row 3"),
    (np.array([-1, 2, 4, 6], np.int64), "must be integers from 0 to 2147483647 (int32), got -1 at row 0"),
    (np.array([0, 4, 2, 6], np.int32), "must be strictly increasing (unique, in time order); row 2 has 2 after 4"),
], ids=["2**31", "wraps to 6", "negative", "decreasing"])
def test_frame_ids_out_of_range_are_refused_not_wrapped(folder, frame_ids, problem):
    _edit_poses(folder / "poses.npz", lambda arrays: arrays.update(frame_ids=frame_ids))
    assert _load_error(folder) == f"{folder / 'poses.npz'}: 'frame_ids' {problem}"


@pytest.mark.parametrize("fps", [1e300, 1001, 0, -30, 0.005, float("nan"), "30", True])
def test_meta_fps_out_of_range_is_refused(folder, fps):
    _edit_json(folder / "meta.json", lambda d: d.update(fps=fps))
    assert _load_error(folder) == (f"{folder / 'meta.json'}: 'fps' must be a number of frames per second from 0.01 "
                                   f"to 1000, got {fps!r}")


@pytest.mark.parametrize("fps", [0.01, 1000])
def test_meta_fps_at_the_ends_of_the_range_is_accepted(folder, fps):
    _edit_json(folder / "meta.json", lambda d: d.update(fps=fps))
    assert data.load_video_folder(folder).fps == fps


# --------------------------------------------------------------------------- motions of animate, render, view
def _motion_npz(path, *, frame_ids=None, fps=None):
    with np.load(data.demo_subject_path() / "train" / "poses.npz") as archive:
        arrays = {"bone_transforms": archive["bone_transforms"][:FRAMES]}
    if frame_ids is not None:
        arrays["frame_ids"] = frame_ids
    if fps is not None:
        arrays["fps"] = np.asarray(fps)
    np.savez(path, **arrays)
    return path


@pytest.fixture(scope="module")
def skeleton():
    return data.load_video_folder(data.demo_subject_path() / "train", max_frames=1).skeleton


@pytest.mark.parametrize("fps", [1e300, 0.0, 5000.0, float("inf")])
def test_a_motion_fps_out_of_range_is_refused(tmp_path, skeleton, fps):
    path = _motion_npz(tmp_path / "motion.npz", fps=fps)
    with pytest.raises(MotionError) as caught:
        load_motion(path, skeleton)
    assert str(caught.value) == f"{path}: fps must be a number of frames per second from 0.01 to 1000, got {fps!r}"


def test_a_motion_folder_fps_out_of_range_is_refused(folder, skeleton):
    _edit_json(folder / "meta.json", lambda d: d.update(fps=1e300))
    with pytest.raises(MotionError) as caught:
        load_motion(folder, skeleton)
    assert str(caught.value) == (f"{folder / 'meta.json'}: fps must be a number of frames per second from 0.01 to "
                                 "1000, got 1e+300")


def test_motion_frame_ids_beyond_int32_are_refused_not_wrapped(tmp_path, skeleton):
    path = _motion_npz(tmp_path / "motion.npz", frame_ids=np.array([0, 1, 2, 2**32 + 3], np.int64))
    with pytest.raises(MotionError) as caught:
        load_motion(path, skeleton)
    assert str(caught.value) == (f"{path}: 'frame_ids' must be integers from 0 to 2147483647 (int32), got "
                                 "4294967299 at row 3")
    # rows in any order stay allowed in a motion (they play in row order)
    path = _motion_npz(tmp_path / "shuffled.npz", frame_ids=np.array([3, 0, 2, 1], np.int64))
    assert load_motion(path, skeleton).frame_ids.tolist() == [3, 0, 2, 1]


BVH = """HIERARCHY
ROOT hips
{
  OFFSET 0 10 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
  End Site
  {
    OFFSET 0 5 0
  }
}
MOTION
Frames: 2
Frame Time: {frame_time}
0 10 0 0 0 0
0 10 0 0 30 0
"""


@pytest.mark.parametrize("frame_time", ["1e-300", "0.0001", "1e300", "0"])
def test_a_bvh_frame_time_out_of_range_is_refused(tmp_path, skeleton, frame_time):
    path = tmp_path / "motion.bvh"
    path.write_text(BVH.replace("{frame_time}", frame_time))
    with pytest.raises(MotionError) as caught:
        load_motion(path, skeleton)
    assert str(caught.value) == (f"{path}, line 13: Frame Time must be from 0.001 to 100 seconds (1000 to 0.01 "
                                 f"frames per second), got {frame_time}")
    path.write_text(BVH.replace("{frame_time}", "0.001"))
    assert load_motion(path, skeleton).fps == 1000.0


# ------------------------------------------------------------------------------------ render --camera cameras.json
def _render_cameras(tmp_path, edit):
    path = tmp_path / "render_cameras.json"
    document = json.loads((data.demo_subject_path() / "train" / "cameras.json").read_text())
    edit(document)
    path.write_text(json.dumps(document))
    return path


@pytest.mark.parametrize("fx,problem", [
    (-190.0, "the camera 'K' must have positive focal lengths, got fx=-190.0, fy=190.95570373535156"),
    (1e30, "the camera 'K' has implausible focal lengths fx=1e+30, fy=190.956 pixels: they must lie within 0.05 "
           "to 50 times the image's larger side (128 pixels), 6.4 to 6400"),
    (1e-30, "the camera 'K' has implausible focal lengths fx=1e-30, fy=190.956 pixels: they must lie within 0.05 "
            "to 50 times the image's larger side (128 pixels), 6.4 to 6400"),
])
def test_render_cameras_need_plausible_focal_lengths(tmp_path, fx, problem):
    path = _render_cameras(tmp_path, lambda d: d["K"][0].__setitem__(0, fx))
    with pytest.raises(ValueError) as caught:
        read_cameras_json(path, 3)
    assert str(caught.value) == f"{path}: {problem}"


@pytest.mark.parametrize("change,problem", [
    (lambda r: r * 1.001, "is not rigid: its rotation part is not orthonormal within 0.0001 (|R^T R - I| = 0.002)"),
    (lambda r: r * [[-1.0], [1.0], [1.0]], "is not rigid: its rotation part has determinant -1, a reflection"),
], ids=["scaled", "reflected"])
def test_render_camera_extrinsics_must_be_rotations(tmp_path, change, problem):
    def edit(document):
        matrix = np.array(document["world_to_camera"])
        matrix[:3, :3] = change(matrix[:3, :3])
        document["frames"] = [{"K": document["K"], "world_to_camera": document["world_to_camera"]},
                              {"K": document["K"], "world_to_camera": matrix.tolist()}]
    path = _render_cameras(tmp_path, edit)
    with pytest.raises(ValueError) as caught:
        read_cameras_json(path, 2)
    assert str(caught.value) == f"{path}: frames[1] 'world_to_camera' {problem}"


def test_render_camera_rotations_within_the_tolerance_are_accepted(tmp_path):
    def edit(document):
        matrix = np.array(document["world_to_camera"])
        matrix[:3, :3] *= 1.00004  # |R^T R - I| = 8e-5
        document["world_to_camera"] = matrix.tolist()
    assert len(read_cameras_json(_render_cameras(tmp_path, edit), 3)) == 3


# ------------------------------------------------------------------------------------------------ the commands
@pytest.fixture(scope="module")
def avatar_file(tmp_path_factory, skeleton):
    avatar = small_avatar(skeleton, seed=3, per_bone=4, cells=8, distill_steps=2)
    return avatar.save(tmp_path_factory.mktemp("plausible_avatar") / "avatar.pt")


def test_the_commands_print_one_line_naming_the_file(avatar_file, tmp_path, capsys):
    motion = _motion_npz(tmp_path / "motion.npz")
    cameras = _render_cameras(tmp_path, lambda d: d["K"][1].__setitem__(1, 1e30))
    assert render.main([str(avatar_file), "--motion", str(motion), "--camera", str(cameras), "-o",
                        str(tmp_path / "frames"), "--device", "cpu", "--no-progress"]) == 2
    error = capsys.readouterr().err
    assert error == (f"error: {cameras}: the camera 'K' has implausible focal lengths fx=190.956, fy=1e+30 pixels: "
                     "they must lie within 0.05 to 50 times the image's larger side (128 pixels), 6.4 to 6400\n")
    bvh = tmp_path / "motion.bvh"
    bvh.write_text(BVH.replace("{frame_time}", "1e-300"))
    assert animate.main([str(avatar_file), "--motion", str(bvh), "-o", str(tmp_path / "out.usda"), "--device",
                         "cpu", "--no-progress"]) == 2
    assert capsys.readouterr().err == (f"error: {bvh}, line 13: Frame Time must be from 0.001 to 100 seconds (1000 "
                                       "to 0.01 frames per second), got 1e-300\n")
    assert not (tmp_path / "frames").exists() and not (tmp_path / "out.usda").exists()
