"""research/perturb_poses.py: a known pose noise, exact in size, reproducible, shared by the views of an instant,
and confined to the image plane or to depth when asked (measured with research/pose_error.py)."""

import json

import numpy as np
import pytest

from research import perturb_poses, pose_error
from warpavatar import data

pytestmark = pytest.mark.research


def _local_angles_deg(poses, reference, parents):
    """Angle [deg] of each joint's local rotation (relative to its parent) of ``poses`` against ``reference``."""
    def local(p):
        rotations = p[..., :3, :3]
        out = rotations.copy()
        for joint, parent in enumerate(parents):
            if parent >= 0:
                out[:, joint] = np.swapaxes(rotations[:, parent], -1, -2) @ rotations[:, joint]
        return out
    relative = np.swapaxes(local(reference), -1, -2) @ local(poses)
    cosine = np.clip((np.trace(relative, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    return np.degrees(np.arccos(cosine))


def test_pose_noise_tool_is_exact_in_size_reproducible_and_shared_by_views(tmp_path):
    tool = perturb_poses
    subject = data.demo_subject_path()
    assert tool.main([str(subject), "-o", str(tmp_path / "noisy"), "--rotation-deg", "4", "--translation-m",
                      "0.03", "--seed", "7"]) == 0
    clean, noisy = data.load_subject(subject), data.load_subject(tmp_path / "noisy")
    parents = clean.train.skeleton.parents
    angles = _local_angles_deg(noisy.train.bone_transforms, clean.train.bone_transforms, parents)
    # every joint turned by the requested angle (to 0.1 degree: the stored rotations are float32 and not exactly
    # orthonormal, which the local angles measured here feel a little in the deepest chains)
    assert np.allclose(angles, 4.0, atol=0.1) and abs(np.median(angles) - 4.0) < 0.005
    roots = [j for j, p in enumerate(parents) if p < 0]
    offsets = noisy.train.bone_transforms[:, roots[0], :3, 3] - clean.train.bone_transforms[:, roots[0], :3, 3]
    rotated_heads = clean.train.bone_transforms[:, roots[0], :3, :3] @ clean.train.skeleton.heads[roots[0]]
    moved = noisy.train.bone_transforms[:, roots[0], :3, :3] @ clean.train.skeleton.heads[roots[0]]
    pivot_offsets = offsets + moved - rotated_heads
    assert np.allclose(np.linalg.norm(pivot_offsets, axis=-1), 0.03, atol=1e-4)
    assert json.loads((tmp_path / "noisy" / "train" / "meta.json").read_text())["poses"] == data.ESTIMATED_POSES
    # a novel view of the same instants got the same noise; novel poses are copied untouched
    view = next(iter(noisy.novel_view))
    train_ids = clean.train.frame_ids.tolist()
    shared = [(row, train_ids.index(i)) for row, i in enumerate(noisy.novel_view[view].frame_ids.tolist())
              if i in train_ids]
    assert shared
    view_rows, train_rows = map(list, zip(*shared))
    assert np.allclose(noisy.novel_view[view].bone_transforms[view_rows], noisy.train.bone_transforms[train_rows],
                       atol=1e-5)
    motion = next(iter(noisy.novel_pose))
    assert np.array_equal(noisy.novel_pose[motion].bone_transforms, clean.novel_pose[motion].bone_transforms)
    # the same seed gives the same noise, another seed another
    tool.perturb_folder(subject / "train", tmp_path / "again", rotation_deg=4.0, translation=0.03, seed=7)
    tool.perturb_folder(subject / "train", tmp_path / "other", rotation_deg=4.0, translation=0.03, seed=8)
    again, other = (data.load_video_folder(tmp_path / name) for name in ("again", "other"))
    assert np.array_equal(again.bone_transforms, noisy.train.bone_transforms)
    assert not np.allclose(other.bone_transforms, noisy.train.bone_transforms, atol=1e-3)
    with pytest.raises(SystemExit):  # a negative size is refused by the argument parser
        tool.main([str(subject), "-o", str(tmp_path / "bad"), "--rotation-deg", "-1"])
    assert not (tmp_path / "bad").exists()


@pytest.mark.parametrize("confine", ["image-plane", "depth"])
def test_perturbation_confined_to_the_image_plane_or_to_depth(tmp_path, confine):
    tool, errors = perturb_poses, pose_error
    source = data.demo_subject_path() / "train"
    tool.perturb_folder(source, tmp_path / "noisy", rotation_deg=5.0, translation=0.03, seed=3, confine=confine)
    clean, noisy = data.load_video_folder(source), data.load_video_folder(tmp_path / "noisy")
    assert json.loads((tmp_path / "noisy" / "meta.json").read_text())["perturbation"]["confine"] == confine
    measured = errors.pose_errors(clean.bone_transforms, noisy.bone_transforms, clean.skeleton.heads,
                                  clean.skeleton.parents, clean.cameras)
    assert np.allclose(measured["rotation_deg"], 5.0, atol=0.02)  # every joint turned by the full angle
    root = int(np.flatnonzero(np.asarray(clean.skeleton.parents) < 0)[0])
    if confine == "image-plane":  # nothing moves along the camera axis, everything across it
        assert measured["along_axis"].max() < 1e-5 and measured["across"].mean() > 0.02
        assert np.allclose(measured["across"][:, root], 0.03, atol=1e-5)
    else:  # the root moves along the axis only; the limbs swing towards or away from the camera
        assert np.allclose(measured["along_axis"][:, root], 0.03, atol=1e-5)
        assert measured["across"][:, root].max() < 1e-5
        assert measured["along_axis"].mean() > measured["across"].mean()
    with pytest.raises(ValueError, match="does not combine with --smooth-frames"):
        tool.perturb_folder(source, tmp_path / "smooth", rotation_deg=5.0, translation=0.03, smooth_frames=4.0,
                            confine=confine)
