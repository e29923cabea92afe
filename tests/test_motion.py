"""Motion sources: BVH parsing and retargeting checked against hand-computed transforms, video folders,
.npz files, and the errors they raise."""

import json

import numpy as np
import pytest

from warpavatar.io.bvh import (BvhError, bvh_forward_kinematics, match_joint_names, parse_bvh, retarget_bvh,
                               up_axis_rotation)
from warpavatar.io.motion import Motion, MotionError, load_motion

try:
    from warpavatar.data import Skeleton
except ImportError:  # pragma: no cover - stand-in with the same fields
    import dataclasses

    @dataclasses.dataclass
    class Skeleton:
        names: list
        parents: np.ndarray
        heads: np.ndarray
        tails: np.ndarray
        up: np.ndarray

# A Y-up BVH, 10 units per metre of the Z-up skeleton below: hips at height 10, spine 15, head 20 (end 22),
# a leg from (2, 5, 0) down to the floor. Frame 0: rest. Frame 1: root moved +1 in X and turned 90 degrees
# about the vertical. Frame 2: spine bent 90 degrees about X. Frame 3: leg rotated X=90 then Y=90.
BVH_TEXT = """HIERARCHY
ROOT Hips
{
  OFFSET 0 10 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
  JOINT Spine
  {
    OFFSET 0 5 0
    CHANNELS 3 Zrotation Xrotation Yrotation
    JOINT Head
    {
      OFFSET 0 5 0
      CHANNELS 3 Zrotation Xrotation Yrotation
      End Site
      {
        OFFSET 0 2 0
      }
    }
  }
  JOINT LeftLeg
  {
    OFFSET 2 -5 0
    CHANNELS 3 Xrotation Yrotation Zrotation
    End Site
    {
      OFFSET 0 -5 0
    }
  }
}
MOTION
Frames: 4
Frame Time: 0.04
0 10 0  0 0 0   0 0 0   0 0 0   0 0 0
1 10 0  0 0 90  0 0 0   0 0 0   0 0 0
0 10 0  0 0 0   0 90 0  0 0 0   0 0 0
0 10 0  0 0 0   0 0 0   0 0 0   90 90 0
"""

# Exact rotation matrices (column vectors, right-handed).
RX90 = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]], dtype=np.float64)
RY90 = np.array([[0, 0, 1], [0, 1, 0], [-1, 0, 0]], dtype=np.float64)
RZ90 = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1]], dtype=np.float64)


def make_skeleton(names=("hips", "spine", "head", "left_leg")) -> Skeleton:
    return Skeleton(
        names=list(names),
        parents=np.array([-1, 0, 1, 0], dtype=np.int32),
        heads=np.array([[0, 0, 1.0], [0, 0, 1.5], [0, 0, 2.0], [0.2, 0, 0.5]], dtype=np.float32),
        tails=np.array([[0, 0, 1.5], [0, 0, 2.0], [0, 0, 2.2], [0.2, 0, 0.0]], dtype=np.float32),
        up=np.array([0, 0, 1], dtype=np.float32),
    )


def rigid(rotation, translation) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = rotation
    out[:3, 3] = translation
    return out


@pytest.fixture
def bvh_path(tmp_path):
    path = tmp_path / "walk.bvh"
    path.write_text(BVH_TEXT)
    return path


def test_parse_bvh(bvh_path):
    bvh = parse_bvh(bvh_path)
    assert bvh.names == ["Hips", "Spine", "Head", "LeftLeg"]
    np.testing.assert_array_equal(bvh.parents, [-1, 0, 1, 0])
    np.testing.assert_array_equal(bvh.offsets[3], [2, -5, 0])
    assert bvh.channels[3] == ("Xrotation", "Yrotation", "Zrotation")
    assert bvh.motion.shape == (4, 15) and bvh.fps == pytest.approx(25.0)
    np.testing.assert_array_equal(bvh.end_site_parents, [2, 3])
    rotations, positions = bvh_forward_kinematics(bvh)
    np.testing.assert_allclose(rotations[0], np.tile(np.eye(3), (4, 1, 1)), atol=1e-12)
    np.testing.assert_allclose(positions[0], [[0, 10, 0], [0, 15, 0], [0, 20, 0], [2, 5, 0]], atol=1e-12)
    # Frame 2: spine bent about X carries the head forward (+Z).
    np.testing.assert_allclose(positions[2, 2], [0, 15, 5], atol=1e-12)
    # Frame 3: channel order X then Y: R = Rx(90) @ Ry(90), not the reverse.
    np.testing.assert_allclose(rotations[3, 3], RX90 @ RY90, atol=1e-12)
    assert not np.allclose(rotations[3, 3], RY90 @ RX90)


def test_retarget_matches_hand_computed(bvh_path):
    bones = retarget_bvh(parse_bvh(bvh_path), make_skeleton())
    assert bones.shape == (4, 4, 4, 4) and bones.dtype == np.float32
    # Frame 0: the rest pose.
    np.testing.assert_allclose(bones[0], np.tile(np.eye(4), (4, 1, 1)), atol=1e-6)
    # Frame 1: a BVH turn about its vertical Y is a turn about our Z; +1 BVH unit in X is +0.1 m in X.
    expected = rigid(RZ90, [0.1, 0, 0])
    for joint in range(4):
        np.testing.assert_allclose(bones[1, joint], expected, atol=1e-6)
    # Frame 2: the spine bends about X (same axis in both frames); the head follows rigidly.
    np.testing.assert_allclose(bones[2, 0], np.eye(4), atol=1e-6)
    np.testing.assert_allclose(bones[2, 1], rigid(RX90, [0, 1.5, 1.5]), atol=1e-6)
    np.testing.assert_allclose(bones[2, 2], rigid(RX90, [0, 1.5, 1.5]), atol=1e-6)
    np.testing.assert_allclose(bones[2, 3], np.eye(4), atol=1e-6)
    # Frame 3: leg rotation Rx(90) Ry(90) in BVH axes; in ours: C R C^T with C = +90 deg about X.
    conversion = RX90
    np.testing.assert_allclose(up_axis_rotation("Y", [0, 0, 1]), conversion, atol=1e-12)
    leg_rotation = conversion @ RX90 @ RY90 @ conversion.T
    head = np.array([0.2, 0, 0.5])
    np.testing.assert_allclose(bones[3, 3], rigid(leg_rotation, head - leg_rotation @ head), atol=1e-6)
    # The posed leg end matches the BVH end site converted to metres: (2, 5, 0) + R (0, -5, 0).
    end_bvh = np.array([2, 5, 0]) + RX90 @ RY90 @ np.array([0, -5, 0])
    end_ours = bones[3, 3] @ np.array([0.2, 0, 0.0, 1])
    np.testing.assert_allclose(end_ours[:3], conversion @ end_bvh * 0.1, atol=1e-6)


def test_retarget_subset_and_unmapped_joints(bvh_path):
    bvh = parse_bvh(bvh_path)
    bones = retarget_bvh(bvh, make_skeleton(), name_map={"hips": "Hips", "head": "Head"})
    # spine and left_leg are unmapped: rigidly attached to their parent (same transform).
    np.testing.assert_allclose(bones[:, 1], bones[:, 0], atol=1e-6)
    np.testing.assert_allclose(bones[:, 3], bones[:, 0], atol=1e-6)
    # Frame 2: the head takes its BVH world rotation (the spine's bend) but pivots at its own rest head.
    np.testing.assert_allclose(bones[2, 2], rigid(RX90, [0, 2.0, 2.0]), atol=1e-6)
    np.testing.assert_allclose(bones[2, 1], np.eye(4), atol=1e-6)
    # Explicit scale: 0.05 m per BVH unit halves the root translation.
    half = retarget_bvh(bvh, make_skeleton(), scale=0.05)
    np.testing.assert_allclose(half[1, 0], rigid(RZ90, [0.05, 0, 0]), atol=1e-6)


def test_name_matching():
    bvh_names = ["mixamorig:Hips", "mixamorig:LeftArm", "RightArm", "Spine"]
    mapping = match_joint_names(["hips", "arm_l", "Arm.R", "spine", "tail"], bvh_names)
    assert mapping == {0: 0, 1: 1, 2: 2, 3: 3}
    assert match_joint_names(["SPINE"], bvh_names) == {0: 3}
    with pytest.raises(BvhError, match="not in the BVH"):
        match_joint_names(["spine"], bvh_names, {"spine": "Chest"})
    with pytest.raises(BvhError, match="not in the skeleton"):
        match_joint_names(["spine"], bvh_names, {"neck": "Spine"})


def test_load_motion_bvh(bvh_path):
    motion = load_motion(bvh_path, make_skeleton(), frames=slice(1, 3))
    assert isinstance(motion, Motion)
    assert motion.fps == pytest.approx(25.0) and motion.frame_ids.tolist() == [1, 2]
    np.testing.assert_allclose(motion.bone_transforms[0, 0], rigid(RZ90, [0.1, 0, 0]), atol=1e-6)
    # Z-up BVH data into a Z-up skeleton: no axis change.
    z_up = load_motion(bvh_path, make_skeleton(), bvh_up="Z", bvh_scale=0.1)
    np.testing.assert_allclose(z_up.bone_transforms[1, 0, :3, :3], np.array([[0, 0, 1], [0, 1, 0], [-1, 0, 0]]),
                               atol=1e-6)  # BVH's 90 degrees about Y stays about Y


def write_folder(folder, bone_transforms, frame_ids, fps=24):
    folder.mkdir()
    np.savez(folder / "poses.npz", bone_transforms=bone_transforms, frame_ids=frame_ids)
    (folder / "meta.json").write_text(json.dumps({"fps": fps}))
    return folder


def random_bones(seed, frames=5, joints=4):
    rng = np.random.default_rng(seed)
    out = np.tile(np.eye(4, dtype=np.float32), (frames, joints, 1, 1))
    q, _ = np.linalg.qr(rng.normal(size=(frames, joints, 3, 3)))
    q *= np.sign(np.linalg.det(q))[..., None, None]
    out[..., :3, :3] = q
    out[..., :3, 3] = rng.normal(size=(frames, joints, 3))
    return out


@pytest.mark.parametrize("seed", [0, 1])
def test_load_motion_folder_and_npz(tmp_path, seed):
    bones = random_bones(seed)
    folder = write_folder(tmp_path / "video", bones, np.arange(0, 25, 5, dtype=np.int32))
    motion = load_motion(folder, make_skeleton())
    np.testing.assert_array_equal(motion.bone_transforms, bones)
    assert motion.fps == 24.0 and motion.frame_ids.tolist() == [0, 5, 10, 15, 20]
    assert motion.bone_transforms.dtype == np.float32 and motion.frame_ids.dtype == np.int32
    every_other = load_motion(folder, make_skeleton(), frames=slice(None, None, 2))
    assert every_other.frame_ids.tolist() == [0, 10, 20]
    np.testing.assert_array_equal(every_other.bone_transforms, bones[::2])
    np.savez(tmp_path / "bare.npz", bone_transforms=bones.astype(np.float64))
    bare = load_motion(tmp_path / "bare.npz", make_skeleton())
    assert bare.fps == 30.0 and bare.frame_ids.tolist() == [0, 1, 2, 3, 4]
    np.testing.assert_array_equal(bare.bone_transforms, bones)


def test_load_motion_errors(tmp_path, bvh_path):
    skeleton = make_skeleton()
    bones = random_bones(2)

    def expect(source, message, **kwargs):
        with pytest.raises(MotionError, match=message) as info:
            load_motion(source, skeleton, **kwargs)
        assert str(source) in str(info.value)

    np.savez(tmp_path / "joints.npz", bone_transforms=bones[:, :3])
    expect(tmp_path / "joints.npz", "3 joints but the skeleton has 4")
    nan = bones.copy()
    nan[3, 2, 0, 1] = np.nan
    np.savez(tmp_path / "nan.npz", bone_transforms=nan)
    expect(tmp_path / "nan.npz", "non-finite.*frame 3, joint 2")
    scaled = bones.copy()
    scaled[1, 1, :3, :3] *= 1.1
    np.savez(tmp_path / "scaled.npz", bone_transforms=scaled)
    expect(tmp_path / "scaled.npz", "frame 1, joint 1 is not rigid")
    mirrored = bones.copy()
    mirrored[4, 0, :3, 0] *= -1
    np.savez(tmp_path / "mirror.npz", bone_transforms=mirrored)
    expect(tmp_path / "mirror.npz", "frame 4, joint 0 is not rigid")
    np.savez(tmp_path / "shape.npz", bone_transforms=bones[..., :3, :])
    expect(tmp_path / "shape.npz", r"shape \[T, J, 4, 4\]")
    np.savez(tmp_path / "other.npz", poses=bones)
    expect(tmp_path / "other.npz", "no 'bone_transforms'")
    (tmp_path / "garbage.npz").write_bytes(b"not a zip file")
    expect(tmp_path / "garbage.npz", "cannot read")
    expect(tmp_path / "absent.npz", "no such file")
    (tmp_path / "motion.fbx").write_bytes(b"")
    expect(tmp_path / "motion.fbx", "unknown motion source")
    (tmp_path / "empty_folder").mkdir()
    expect(tmp_path / "empty_folder", "no poses.npz")
    folder = write_folder(tmp_path / "badfps", bones, np.arange(5, dtype=np.int32), fps=-1)
    expect(folder, "fps")
    np.savez(tmp_path / "ok.npz", bone_transforms=bones)
    expect(tmp_path / "ok.npz", "no frames selected", frames=slice(10, 20))
    with pytest.raises(TypeError, match="slice"):
        load_motion(tmp_path / "ok.npz", skeleton, frames=[0, 1])

    # BVH errors.
    renamed = make_skeleton(("root", "torso", "skull", "shin"))
    with pytest.raises(MotionError, match="no joint of the skeleton maps") as info:
        load_motion(bvh_path, renamed)
    assert str(bvh_path) in str(info.value)
    expect(bvh_path, "not in the BVH", name_map={"hips": "Pelvis"})
    broken = tmp_path / "broken.bvh"
    broken.write_text(BVH_TEXT.replace("CHANNELS 3 Xrotation Yrotation Zrotation", "CHANNELS 3 Xrotation Wrot Z"))
    expect(broken, "line 23: bad channels")
    short = tmp_path / "short.bvh"
    short.write_text(BVH_TEXT.rsplit("\n", 2)[0] + "\n")
    expect(short, "MOTION has 45 values, expected")
    no_motion = tmp_path / "nomotion.bvh"
    no_motion.write_text(BVH_TEXT.split("MOTION")[0])
    expect(no_motion, "no MOTION")
    not_bvh = tmp_path / "text.bvh"
    not_bvh.write_text("hello world\n")
    expect(not_bvh, "not a BVH file")
