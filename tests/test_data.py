"""Tests of warpavatar.data: the demo subject, reading and writing video folders, one test per class of bad
input (each must raise VideoFolderError naming the file), resizing, the video-file path and the importer."""

import json
import pickle
import shutil
from dataclasses import replace

import cv2

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from warpavatar.data import (Camera, Skeleton, VideoFolder, VideoFolderError, demo_subject_path,
                             import_instantavatar, load_subject, load_video_folder, write_video_folder)

SIZE = 16


def _skeleton(joint_count=3):
    heads = np.stack([[0.0, 0.0, 0.1 * j] for j in range(joint_count)])
    return Skeleton(names=[f"joint{j}" for j in range(joint_count)], parents=np.arange(joint_count) - 1,
                    heads=heads, tails=heads + [0.0, 0.0, 0.1], up=np.array([0.0, 0.0, 1.0]))


def _bone_transforms(frame_count, joint_count, seed):
    rotations = Rotation.random(frame_count * joint_count, random_state=seed).as_matrix()
    transforms = np.tile(np.eye(4), (frame_count, joint_count, 1, 1))
    transforms[..., :3, :3] = rotations.reshape(frame_count, joint_count, 3, 3)
    transforms[..., :3, 3] = np.random.default_rng(seed).normal(scale=0.1, size=(frame_count, joint_count, 3))
    return transforms.astype(np.float32)


def _camera(size=SIZE):
    world_to_camera = np.eye(4)
    world_to_camera[2, 3] = 3.0
    K = [[20.0, 0.0, (size - 1) / 2], [0.0, 20.0, (size - 1) / 2], [0.0, 0.0, 1.0]]
    return Camera(K=K, world_to_camera=world_to_camera, width=size, height=size)


def _video(frame_ids=(0, 1, 2), size=SIZE, seed=0, images=None):
    rng = np.random.default_rng(seed)
    frame_count = len(frame_ids)
    skeleton = _skeleton()
    bone_transforms = _bone_transforms(frame_count, skeleton.joint_count, seed)
    camera = _camera(size)
    if images is None:
        images = rng.integers(1, 255, size=(frame_count, size, size, 3), dtype=np.uint8)
    masks = np.where(rng.random((frame_count, size, size)) > 0.5, 255, 0).astype(np.uint8)
    joint_positions = (np.einsum("tjab,jb->tja", bone_transforms[..., :3, :3], skeleton.heads)
                       + bone_transforms[..., :3, 3]).astype(np.float32)
    return VideoFolder(root=None, frame_ids=np.asarray(frame_ids, dtype=np.int32), images=images, masks=masks,
                       cameras=[camera] * frame_count, skeleton=skeleton, bone_transforms=bone_transforms,
                       joint_positions=joint_positions, background=np.array([0.0, 0.5, 1.0]), fps=25.0,
                       meta={"source": "test"})


@pytest.fixture
def folder(tmp_path):
    """A small valid video folder: 3 frames of 16x16 pixels, 3 joints, masks, fixed camera."""
    return write_video_folder(_video(), tmp_path / "video")


def _expect_error(path, file_name, keyword):
    with pytest.raises(VideoFolderError) as caught:
        load_video_folder(path)
    message = str(caught.value)
    assert file_name in message, message
    assert keyword.lower() in message.lower(), message
    return caught.value


def _edit_json(path, edit):
    data = json.loads(path.read_text())
    edit(data)
    path.write_text(json.dumps(data))


def _edit_poses(path, edit):
    with np.load(path) as archive:
        arrays = dict(archive)
    edit(arrays)
    np.savez(path, **arrays)


# ----------------------------------------------------------------------------------------------------------
# Valid data


def test_demo_subject_loads():
    subject = load_subject(demo_subject_path())
    train = subject.train
    assert train.frame_count >= 30 and train.width == train.height == 128
    assert train.images.dtype == np.uint8 and train.images.shape == (train.frame_count, 128, 128, 3)
    assert train.masks is not None and set(np.unique(train.masks)) <= {0, 255}
    assert train.skeleton.joint_count == train.bone_transforms.shape[1] == 41
    assert train.fixed_camera and train.fps == 30.0
    assert "CC0" in subject.license_text and "Reduced" in subject.license_text
    assert len(subject.novel_view) == 1 and len(subject.novel_pose) == 1
    for folders in (subject.novel_view, subject.novel_pose):
        for name in folders:
            held_out = folders[name]
            assert 10 <= held_out.frame_count <= 20
            assert held_out.skeleton.names == train.skeleton.names
    # The cropped and resized cameras still put the posed joints on the subject.
    for video in (train, *subject.novel_view.values(), *subject.novel_pose.values()):
        pixels, depth = video.cameras[0].project(video.joint_positions)
        assert np.all(depth > 0)
        columns = np.clip(np.round(pixels[..., 0]).astype(int), 0, video.width - 1)
        rows = np.clip(np.round(pixels[..., 1]).astype(int), 0, video.height - 1)
        inside = video.masks[np.arange(video.frame_count)[:, None], rows, columns] > 0
        assert inside.mean() > 0.9, (video.root, inside.mean())


def test_a_folder_without_a_declared_background_is_rewritten_without_one(tmp_path):
    # real footage declares no background: read back and written again it must not gain a black one, which would
    # make its frames, room and all, a fit's target (--target auto)
    real = replace(_video(), background=np.zeros(3), meta={"source": "a phone"})
    first = load_video_folder(write_video_folder(real, tmp_path / "real"))
    assert "background" not in first.meta
    again = load_video_folder(write_video_folder(first, tmp_path / "again"))
    assert "background" not in again.meta and again.background.tolist() == [0.0, 0.0, 0.0]
    rendered = load_video_folder(write_video_folder(replace(real, meta={"background": [0, 0, 0]}), tmp_path / "r"))
    assert rendered.meta["background"] == [0.0, 0.0, 0.0]


def test_write_and_load_round_trip(folder):
    expected = _video()
    video = load_video_folder(folder)
    np.testing.assert_array_equal(video.images, expected.images)
    np.testing.assert_array_equal(video.masks, expected.masks)
    np.testing.assert_array_equal(video.frame_ids, expected.frame_ids)
    np.testing.assert_allclose(video.bone_transforms, expected.bone_transforms)
    np.testing.assert_allclose(video.joint_positions, expected.joint_positions)
    np.testing.assert_allclose(video.intrinsics[0], expected.cameras[0].K)
    assert video.fixed_camera and len(video.cameras) == 3
    assert video.fps == 25.0 and video.background.tolist() == [0.0, 0.5, 1.0]
    assert video.skeleton.to_json_dict() == expected.skeleton.to_json_dict()
    assert not folder.with_name("video.tmp").exists()
    # Selection: every 2nd row, at most 1.
    subset = load_video_folder(folder, frame_stride=2, max_frames=1)
    assert subset.frame_ids.tolist() == [0] and subset.images.shape[0] == 1
    assert load_video_folder(folder, frame_stride=2).frame_ids.tolist() == [0, 2]


def test_defaults_without_meta_and_per_frame_cameras(folder):
    (folder / "meta.json").unlink()
    shutil.rmtree(folder / "masks")
    world_to_cameras = [np.eye(4) for _ in range(3)]
    for index, matrix in enumerate(world_to_cameras):
        matrix[:3, :3] = Rotation.from_euler("z", 10.0 * index, degrees=True).as_matrix()
        matrix[2, 3] = 3.0 + index
    _edit_json(folder / "cameras.json",
               lambda data: data.update(frames=[{"K": data["K"], "world_to_camera": m.tolist()}
                                                for m in world_to_cameras]))
    video = load_video_folder(folder)
    assert video.masks is None and video.fps == 30.0 and video.background.tolist() == [0.0, 0.0, 0.0]
    assert not video.fixed_camera
    np.testing.assert_allclose(video.world_to_cameras, np.stack(world_to_cameras), atol=1e-6)


def test_error_is_picklable_and_names_path(tmp_path):
    error = VideoFolderError(tmp_path / "poses.npz", "something is wrong")
    copy = pickle.loads(pickle.dumps(error))
    assert str(copy) == str(error) and copy.path == error.path and isinstance(copy, ValueError)


# ----------------------------------------------------------------------------------------------------------
# Bad input: one test per class, each checks the named file and a keyword.


def test_missing_folder(tmp_path):
    _expect_error(tmp_path / "nowhere", "nowhere", "no such")


@pytest.mark.parametrize("file_name", ["cameras.json", "skeleton.json", "poses.npz"])
def test_missing_file(folder, file_name):
    (folder / file_name).unlink()
    _expect_error(folder, file_name, "missing")


def test_missing_frames_and_video(folder):
    shutil.rmtree(folder / "frames")
    _expect_error(folder, "frames", "neither frames/ nor a video")


def test_missing_frame_lists_ids(folder):
    (folder / "frames" / "000001.png").unlink()
    (folder / "frames" / "000002.png").unlink()
    error = _expect_error(folder, "frames", "missing")
    assert "000001" in str(error) and "000002" in str(error)


def test_unreadable_frame(folder):
    (folder / "frames" / "000002.png").write_bytes(b"not a png")
    _expect_error(folder, "000002.png", "cannot be read")


def test_unreadable_json_and_npz(folder):
    (folder / "cameras.json").write_text("{ not json")
    _expect_error(folder, "cameras.json", "JSON")
    (folder / "cameras.json").unlink()
    write_video_folder(_video(), folder, overwrite=True)
    (folder / "poses.npz").write_bytes(b"garbage")
    _expect_error(folder, "poses.npz", "cannot be read")


def test_badly_named_frame(folder):
    shutil.copy(folder / "frames" / "000000.png", folder / "frames" / "frame_3.png")
    _expect_error(folder, "frames", "6-digit")


def test_frame_count_mismatch(folder):
    shutil.copy(folder / "frames" / "000000.png", folder / "frames" / "000007.png")
    error = _expect_error(folder, "poses.npz", "frame count mismatch")
    assert "000007" in str(error)


def test_mask_count_mismatch(folder):
    (folder / "masks" / "000001.png").unlink()
    _expect_error(folder, "masks", "missing")
    write_video_folder(_video(), folder, overwrite=True)
    shutil.copy(folder / "masks" / "000000.png", folder / "masks" / "000009.png")
    _expect_error(folder, "poses.npz", "mismatch")


def test_frame_ids_count_mismatch(folder):
    _edit_poses(folder / "poses.npz", lambda arrays: arrays.update(frame_ids=np.array([0, 1], dtype=np.int32)))
    _expect_error(folder, "poses.npz", "frame count mismatch")


def test_frame_ids_not_increasing(folder):
    _edit_poses(folder / "poses.npz", lambda arrays: arrays.update(frame_ids=np.array([0, 2, 1], dtype=np.int32)))
    _expect_error(folder, "poses.npz", "strictly increasing")


def test_image_size_mismatch_with_cameras(folder):
    _edit_json(folder / "cameras.json", lambda data: data.update(width=SIZE + 4))
    _expect_error(folder, "000000.png", "size mismatch")


def test_image_size_mismatch_between_frames_and_masks(folder):
    cv2.imwrite(str(folder / "masks" / "000001.png"), np.zeros((SIZE, SIZE + 2), np.uint8))
    _expect_error(folder, "masks/000001.png", "size mismatch")


def test_mask_with_colour_channels(folder):
    cv2.imwrite(str(folder / "masks" / "000001.png"),
                np.random.default_rng(0).integers(0, 255, (SIZE, SIZE, 3), dtype=np.uint8))
    _expect_error(folder, "masks/000001.png", "single-channel")


@pytest.mark.parametrize("where", ["bone_transforms", "joint_positions"])
def test_non_finite_poses(folder, where):
    def edit(arrays):
        arrays[where][1, 0, 0] = np.nan
    _edit_poses(folder / "poses.npz", edit)
    _expect_error(folder, "poses.npz", "non-finite")


@pytest.mark.parametrize("key", ["K", "world_to_camera"])
def test_non_finite_camera(folder, key):
    def edit(data):
        data[key][0][0] = float("inf")
    _edit_json(folder / "cameras.json", edit)
    _expect_error(folder, "cameras.json", "non-finite")


def test_non_finite_skeleton(folder):
    _edit_json(folder / "skeleton.json", lambda data: data["joints"][1]["head"].__setitem__(2, float("nan")))
    _expect_error(folder, "skeleton.json", "non-finite")


@pytest.mark.parametrize("defect,keyword", [("scaled", "orthonormal"), ("reflection", "reflection"),
                                            ("last_row", "last row")])
def test_bone_transforms_not_rigid(folder, defect, keyword):
    def edit(arrays):
        transform = arrays["bone_transforms"][2, 1]
        if defect == "scaled":
            transform[:3, :3] *= 1.01
        elif defect == "reflection":
            transform[:3, 0] *= -1.0
        else:
            transform[3, 0] = 0.5
    _edit_poses(folder / "poses.npz", edit)
    error = _expect_error(folder, "poses.npz", keyword)
    assert "frame row 2, joint 1" in str(error)


@pytest.mark.parametrize("parents,keyword", [([-1, 2, 1], "cycle"), ([-1, 0, 3], "outside"),
                                             ([1, 2, 0], "no root"), ([-1, 1, 0], "cycle")])
def test_parents_not_a_tree(folder, parents, keyword):
    def edit(data):
        for joint, parent in zip(data["joints"], parents):
            joint["parent"] = parent
    _edit_json(folder / "skeleton.json", edit)
    _expect_error(folder, "skeleton.json", keyword)


@pytest.mark.parametrize("edit,keyword", [
    (lambda data: data.update(format="other/1"), "format"),
    (lambda data: data["joints"][2].update(name="joint0"), "unique"),
    (lambda data: data["joints"][1].pop("tail"), "tail"),
    (lambda data: data.update(joints=[]), "non-empty"),
])
def test_skeleton_malformed(folder, edit, keyword):
    _edit_json(folder / "skeleton.json", edit)
    _expect_error(folder, "skeleton.json", keyword)


def test_forest_is_allowed(folder):
    _edit_json(folder / "skeleton.json", lambda data: data["joints"][2].update(parent=-1))
    assert load_video_folder(folder).skeleton.parents.tolist() == [-1, 0, -1]


@pytest.mark.parametrize("key,value,keyword", [
    ("K", [[20.0, 0.0, 7.5], [0.0, 20.0, 7.5]], "shape [3, 3]"),
    ("K", [[20.0, 0.0, 7.5], [0.0, 20.0, 7.5], [0.0, 1.0, 1.0]], "last row"),
    ("K", [[-20.0, 0.0, 7.5], [0.0, 20.0, 7.5], [0.0, 0.0, 1.0]], "focal"),
    ("world_to_camera", np.eye(4)[:3].tolist(), "shape [4, 4]"),
    ("world_to_camera", (np.eye(4) * [2.0, 1.0, 1.0, 1.0]).tolist(), "not rigid"),
    ("width", 0, "positive integer"),
])
def test_bad_camera(folder, key, value, keyword):
    _edit_json(folder / "cameras.json", lambda data: data.update({key: value}))
    _expect_error(folder, "cameras.json", keyword)


def test_joint_count_mismatch(folder):
    _edit_json(folder / "skeleton.json", lambda data: data["joints"].pop())
    _expect_error(folder, "poses.npz", "joint count mismatch")


def test_per_frame_camera_count_mismatch(folder):
    _edit_json(folder / "cameras.json",
               lambda data: data.update(frames=[{"K": data["K"], "world_to_camera": data["world_to_camera"]}] * 2))
    _expect_error(folder, "cameras.json", "per-frame camera count mismatch")


def test_bad_meta(folder):
    _edit_json(folder / "meta.json", lambda data: data.update(fps=-1))
    _expect_error(folder, "meta.json", "fps")
    _edit_json(folder / "meta.json", lambda data: data.update(fps=30, background=[0.0, 2.0, 0.0]))
    _expect_error(folder, "meta.json", "background")


def test_bad_options(folder):
    with pytest.raises(ValueError, match="scale"):
        load_video_folder(folder, scale=0.0)
    with pytest.raises(ValueError, match="frame_stride"):
        load_video_folder(folder, frame_stride=0)
    with pytest.raises(TypeError, match="max_frames"):
        load_video_folder(folder, max_frames=1.5)


def test_subject_errors(tmp_path, folder):
    _expect_error_subject = pytest.raises(VideoFolderError, match="train")
    with _expect_error_subject:
        load_subject(tmp_path)
    # A held-out folder whose skeleton differs is reported when it is read.
    subject_dir = tmp_path / "subject"
    shutil.copytree(folder, subject_dir / "train")
    shutil.copytree(folder, subject_dir / "novel_view" / "cam_a")
    _edit_json(subject_dir / "novel_view" / "cam_a" / "skeleton.json",
               lambda data: data["joints"][1].update(name="renamed"))
    subject = load_subject(subject_dir)
    assert list(subject.novel_view) == ["cam_a"] and len(subject.novel_pose) == 0 and subject.license_text is None
    with pytest.raises(VideoFolderError, match="skeleton differs"):
        subject.novel_view["cam_a"]


# ----------------------------------------------------------------------------------------------------------
# Resizing, video files, importer


@pytest.mark.parametrize("scale", [0.5, 0.25])
def test_scale_keeps_projection_consistent(tmp_path, scale):
    size = 32
    image = np.zeros((1, size, size, 3), np.uint8)
    image[0, 16:24, 8:16] = 200  # an 8x8 block with centre (column 11.5, row 19.5), aligned to both scales
    video = _video(frame_ids=(0,), size=size, images=image)
    video.masks[:] = 0
    video.masks[0, 16:24, 8:16] = 255
    # Put joint 0's posed head on the block's centre: back-project (11.5, 19.5) at depth 3 (camera at z = -3).
    camera = video.cameras[0]
    point = np.array([(11.5 - camera.K[0, 2]) / camera.K[0, 0] * 3.0, (19.5 - camera.K[1, 2]) / camera.K[1, 1] * 3.0,
                      0.0])
    video.joint_positions[0, 0] = point
    path = write_video_folder(video, tmp_path / "video")
    scaled = load_video_folder(path, scale=scale)
    assert scaled.width == scaled.height == round(size * scale)
    pixel, _ = scaled.cameras[0].project(scaled.joint_positions[0, 0])
    weights = scaled.images[0, ..., 0].astype(np.float64)
    rows, columns = np.mgrid[:scaled.height, :scaled.width]
    centroid = np.array([(weights * columns).sum(), (weights * rows).sum()]) / weights.sum()
    np.testing.assert_allclose(pixel, centroid, atol=1e-4)
    np.testing.assert_allclose(pixel, (np.array([11.5, 19.5]) + 0.5) * scale - 0.5, atol=1e-4)
    mask = scaled.masks[0]
    assert set(np.unique(mask)) <= {0, 255}
    mask_rows, mask_columns = np.nonzero(mask)
    np.testing.assert_allclose([mask_columns.mean(), mask_rows.mean()], centroid, atol=1e-4)


def test_video_file(tmp_path):
    frame_ids = (0, 2, 3)
    colours = np.array([[250, 20, 20], [20, 250, 20], [20, 20, 250], [200, 200, 20]], np.uint8)
    video = _video(frame_ids=frame_ids, size=32, images=np.repeat(colours[list(frame_ids)][:, None, None], 32, 1)
                   .repeat(32, 2))
    path = write_video_folder(video, tmp_path / "video")
    shutil.rmtree(path / "frames")
    writer = cv2.VideoWriter(str(path / "clip.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 25, (32, 32))
    assert writer.isOpened()
    for colour in colours:  # the video has frames 0..3; poses use 0, 2 and 3
        writer.write(np.full((32, 32, 3), colour[::-1], np.uint8))  # OpenCV writes BGR
    writer.release()
    loaded = load_video_folder(path)
    assert loaded.images.shape == (3, 32, 32, 3)
    mean_colours = loaded.images.reshape(3, -1, 3).mean(axis=1)
    np.testing.assert_allclose(mean_colours, colours[list(frame_ids)], atol=12)
    assert load_video_folder(path, scale=0.5).images.shape == (3, 16, 16, 3)
    # Frame ids past the end of the video are an error naming the video file.
    _edit_poses(path / "poses.npz", lambda arrays: arrays.update(frame_ids=np.array([0, 2, 9], np.int32)))
    shutil.rmtree(path / "masks")
    _expect_error(path, "clip.mp4", "frame count mismatch")


def _instantavatar_source(root, frame_count=3, size=SIZE, seed=1):
    rng = np.random.default_rng(seed)
    (root / "images").mkdir(parents=True)
    (root / "masks").mkdir()
    images = rng.integers(0, 255, size=(frame_count, size, size, 3), dtype=np.uint8)
    masks = rng.random((frame_count, size, size)) > 0.5
    for index in range(frame_count):
        cv2.imwrite(str(root / "images" / f"image_{index:04d}.png"), images[index][..., ::-1])
        np.save(root / "masks" / f"mask_{index:04d}.npy", masks[index].astype(np.float32))
    camera = _camera(size)
    np.savez(root / "cameras.npz", intrinsic=camera.K.astype(np.float64),
             extrinsic=camera.world_to_camera.astype(np.float64), height=size, width=size)
    skeleton = _skeleton()
    (root / "skeleton.json").write_text(json.dumps(skeleton.to_json_dict()))
    transforms = _bone_transforms(frame_count, skeleton.joint_count, seed)
    np.savez(root / "bones.npz", bone_transforms=transforms)
    return images, masks, camera, transforms


def test_import_instantavatar_round_trip(tmp_path):
    source = tmp_path / "people_snapshot"
    images, masks, camera, transforms = _instantavatar_source(source)
    destination = import_instantavatar(source, tmp_path / "imported", skeleton_json=source / "skeleton.json",
                                       bone_transforms_npz=source / "bones.npz", fps=24.0)
    video = load_video_folder(destination)
    np.testing.assert_array_equal(video.images, images)
    np.testing.assert_array_equal(video.masks, np.where(masks, 255, 0))
    np.testing.assert_array_equal(video.frame_ids, [0, 1, 2])
    np.testing.assert_allclose(video.bone_transforms, transforms)
    np.testing.assert_allclose(video.cameras[0].K, camera.K)
    np.testing.assert_allclose(video.cameras[0].world_to_camera, camera.world_to_camera)
    assert video.fps == 24.0 and video.joint_positions is None
    assert not (tmp_path / "imported.tmp").exists()
    with pytest.raises(FileExistsError):
        import_instantavatar(source, destination, skeleton_json=source / "skeleton.json",
                             bone_transforms_npz=source / "bones.npz")


def test_import_instantavatar_errors(tmp_path):
    source = tmp_path / "src"
    _instantavatar_source(source)
    np.savez(source / "bones.npz", bone_transforms=_bone_transforms(2, 3, 0))
    with pytest.raises(VideoFolderError, match=r"bones\.npz.*frame count mismatch"):
        import_instantavatar(source, tmp_path / "out", skeleton_json=source / "skeleton.json",
                             bone_transforms_npz=source / "bones.npz")
    # A non-rigid transform is found by the final validation and reported against the user's file.
    transforms = _bone_transforms(3, 3, 0)
    transforms[1, 2, :3, :3] *= 2.0
    np.savez(source / "bones.npz", bone_transforms=transforms)
    with pytest.raises(VideoFolderError, match=r"bones\.npz.*not rigid"):
        import_instantavatar(source, tmp_path / "out", skeleton_json=source / "skeleton.json",
                             bone_transforms_npz=source / "bones.npz")
    assert not (tmp_path / "out").exists() and not (tmp_path / "out.tmp").exists()
    (source / "cameras.npz").unlink()
    with pytest.raises(VideoFolderError, match=r"cameras\.npz.*missing"):
        import_instantavatar(source, tmp_path / "out", skeleton_json=source / "skeleton.json",
                             bone_transforms_npz=source / "bones.npz")


def test_staged_folder_commits_whole_or_not_at_all(tmp_path):
    from warpavatar.data import staged_folder

    destination = tmp_path / "out"
    with staged_folder(destination) as staging:
        assert staging.parent == tmp_path and staging.name.startswith("out.tmp-") and not destination.exists()
        (staging / "a.txt").write_text("first")
    assert (destination / "a.txt").read_text() == "first" and not staging.exists()
    # a failure half-way leaves the previous folder as it was and no temporary folder
    with pytest.raises(RuntimeError, match="half-way"):
        with staged_folder(destination, overwrite=True) as staging:
            (staging / "a.txt").write_text("second")
            raise RuntimeError("half-way")
    assert (destination / "a.txt").read_text() == "first"
    assert sorted(path.name for path in tmp_path.iterdir()) == ["out"]
    with pytest.raises(FileExistsError, match="out: already exists"):
        with staged_folder(destination):
            pass
    with staged_folder(destination, overwrite=True) as staging:
        (staging / "b.txt").write_text("replaced")
    assert sorted(path.name for path in destination.iterdir()) == [".warpavatar-output", "b.txt"]
    assert sorted(path.name for path in tmp_path.iterdir()) == ["out"]
    # a folder it did not write is never replaced, even with overwrite
    (tmp_path / "photos").mkdir()
    (tmp_path / "photos" / "holiday.jpg").write_bytes(b"mine")
    with pytest.raises(FileExistsError, match="photos: the folder exists and holds files warpavatar did not write"):
        with staged_folder(tmp_path / "photos", overwrite=True):
            pass
    assert [path.name for path in (tmp_path / "photos").iterdir()] == ["holiday.jpg"]


def test_the_prepared_skeleton_round_trips_through_skeleton_json(tmp_path):
    """warpavatar-prepare builds the same Skeleton class the loader reads (float64 while it fits)."""
    from warpavatar.data.reader import read_skeleton
    from warpavatar.data.writer import write_json
    from warpavatar.prepare import skeleton_fit

    body = skeleton_fit.BodyMeasurements(
        torso_length=0.52, neck_length=0.19, hip_width=0.27, shoulder_width=0.38, upper_arm=0.3, forearm=0.25,
        hand=0.09, hand_width=0.08, thigh=0.44, shin=0.42, foot=0.18, ear_width=0.15, nose_offset=0.1,
        nose_angle_rad=1.7)
    skeleton = skeleton_fit.build_rest_skeleton(body).skeleton
    assert isinstance(skeleton, Skeleton) and skeleton.heads.dtype == np.float64
    write_json(tmp_path / "skeleton.json", skeleton.to_json_dict(decimals=6))
    loaded = read_skeleton(tmp_path / "skeleton.json")
    assert loaded.names == list(skeleton_fit.JOINT_NAMES) and loaded.heads.dtype == np.float32
    assert np.array_equal(loaded.parents, skeleton.parents)
    np.testing.assert_allclose(loaded.heads, skeleton.heads, atol=1e-6)
    np.testing.assert_allclose(loaded.tails, skeleton.tails, atol=1e-6)
    with pytest.raises(ValueError, match="dtype must be numpy.float32 or numpy.float64"):
        Skeleton(names=["a"], parents=[-1], heads=np.zeros((1, 3)), tails=np.ones((1, 3)), dtype=np.int32)
