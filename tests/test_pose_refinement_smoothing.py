"""The pose prior's target, the given motion smoothed in time: on a synthetic motion of known smoothness with
independent per-frame noise of known size, it comes clearly closer to the clean motion than the noisy one is, it
leaves a clean motion nearly as it is, it shrugs off single wild frames, it never averages frames far apart in
time; in a fit, the corrections start at it."""

import math

import pytest
import torch

from research.perturb_poses import perturb_folder
from warpavatar import data
from warpavatar.fit import Trainer, preset
from warpavatar.model.kinematics import (ancestor_jumps, axis_angle_from_matrix, axis_angle_to_matrix,
                                         corrected_transforms, local_rotations, posed_pivots, smoothing_corrections)
from warpavatar.extensions.pose_refinement import PoseRefinementOptions

DEFAULT_WINDOW = PoseRefinementOptions().pose_prior_window  # [s], the widest window of the fit's default

PARENTS = [-1, 0, 1, 2, 1, 4, 0, 6]
FPS = 30.0


def _smooth_motion(frame_count: int, *, fps: float = FPS, seed: int = 0):
    """A motion [T,J,4,4] of PARENTS whose every joint turns smoothly (each axis-angle component a sine of up to
    0.5 rad at 0.3-1.5 Hz) and whose root sways and walks, with its rest pivots [J,3] and its times [T] [s]."""
    generator = torch.Generator().manual_seed(seed)
    joint_count = len(PARENTS)
    heads = 0.3 * torch.randn(joint_count, 3, generator=generator, dtype=torch.float64)
    times = torch.arange(frame_count, dtype=torch.float64) / fps
    amplitude = 0.5 * torch.rand(joint_count, 3, generator=generator, dtype=torch.float64)
    frequency = 0.3 + 1.2 * torch.rand(joint_count, 3, generator=generator, dtype=torch.float64)
    phase = 2 * math.pi * torch.rand(joint_count, 3, generator=generator, dtype=torch.float64)
    angles = amplitude * torch.sin(2 * math.pi * frequency * times[:, None, None] + phase)
    rest = torch.eye(4, dtype=torch.float64).repeat(frame_count, joint_count, 1, 1)
    root = torch.stack([0.3 * torch.sin(times), 0.05 * torch.cos(3 * times), 1.2 * times], dim=-1)
    # the rest pose turned joint by joint and moved at the root is the motion (the correction's own definition)
    return corrected_transforms(rest, heads, ancestor_jumps(PARENTS), angles, root), heads, times


def _noise(frame_count: int, *, degrees: float, metres: float, seed: int):
    """Independent per-frame noise of exact size: axis-angle turns [T,J,3] and root offsets [T,3]."""
    generator = torch.Generator().manual_seed(seed)
    turns = torch.randn(frame_count, len(PARENTS), 3, generator=generator, dtype=torch.float64)
    offsets = torch.randn(frame_count, 3, generator=generator, dtype=torch.float64)
    return (math.radians(degrees) * turns / turns.norm(dim=-1, keepdim=True),
            metres * offsets / offsets.norm(dim=-1, keepdim=True))


def _errors(poses, reference, heads):
    """Per frame and joint: the local rotations' angle apart [deg] [T,J]; per frame: the roots' distance [T]."""
    local, truth = local_rotations(poses, PARENTS), local_rotations(reference, PARENTS)
    angles = torch.rad2deg(axis_angle_from_matrix(truth.transpose(-1, -2) @ local).norm(dim=-1))
    return angles, (posed_pivots(poses, heads)[:, 0] - posed_pivots(reference, heads)[:, 0]).norm(dim=-1)


def _smoothed(poses, heads, times, **options):
    rotation, translation = smoothing_corrections(poses, heads, PARENTS, times, **options)
    return corrected_transforms(poses, heads, ancestor_jumps(PARENTS), rotation, translation)


def test_axis_angle_from_matrix_inverts_axis_angle_to_matrix():
    generator = torch.Generator().manual_seed(3)
    directions = torch.randn(200, 3, generator=generator, dtype=torch.float64)
    directions = directions / directions.norm(dim=-1, keepdim=True)
    angles = torch.cat([torch.tensor([0.0, 1e-9, 1e-5, 3.1]), torch.rand(196, generator=generator) * 3.0])
    vectors = directions * angles[:, None].double()
    assert torch.allclose(axis_angle_from_matrix(axis_angle_to_matrix(vectors)), vectors, atol=1e-9)


@pytest.mark.parametrize("fps, bound", [(30.0, 0.6), (60.0, 0.45)])
def test_smoothed_target_removes_most_of_independent_noise(fps, bound):
    # 3 s of motion; 5 degrees per joint and 2 cm at the root, independent per frame. The default windows (up to
    # 0.45 s either side, where the motion allows) fit up to 27 frames at 30 fps: a quadratic fit over 9 frames
    # keeps 0.51 of white noise (Savitzky-Golay's centre coefficient), over 27 about 0.3, a little more at the ends
    frame_count = int(3 * fps)
    clean, heads, times = _smooth_motion(frame_count, fps=fps)
    turns, offsets = _noise(frame_count, degrees=5.0, metres=0.02, seed=1)
    noisy = corrected_transforms(clean, heads, ancestor_jumps(PARENTS), turns, offsets)
    given_angles, given_offsets = _errors(noisy, clean, heads)
    assert torch.allclose(given_angles, torch.full_like(given_angles, 5.0), atol=1e-6)  # the noise is exact
    angles, offsets = _errors(_smoothed(noisy, heads, times, window=DEFAULT_WINDOW), clean, heads)
    assert angles.mean() < bound * 5.0, float(angles.mean())
    assert offsets.mean() < bound * 0.02, float(offsets.mean())
    # every frame a window away from the ends is clearly better (at the ends the fit extrapolates from one side,
    # which keeps about 0.9 of the noise)
    inner = angles[int(DEFAULT_WINDOW * fps):-int(DEFAULT_WINDOW * fps)].mean(1)
    assert inner.max() < 0.75 * 5.0, float(inner.max())


def test_smoothed_target_leaves_a_clean_motion_nearly_as_it_is():
    clean, heads, times = _smooth_motion(90)
    angles, offsets = _errors(_smoothed(clean, heads, times, window=DEFAULT_WINDOW), clean, heads)
    # components up to 1.5 Hz, up to 0.5 rad: a quadratic fit over +-0.13 s keeps them to within a few 0.01 deg
    assert angles.mean() < 0.1 and angles.max() < 0.5, (float(angles.mean()), float(angles.max()))
    assert offsets.max() < 1e-4  # the root's sway at 0.16 and 0.48 Hz and its steady walk [m]


def test_a_sudden_move_without_noise_is_kept():
    # one joint kicks through 1.2 rad in 0.15 s (8 rad/s, starting and stopping at once) on top of the smooth
    # motion: the widest window alone rounds its corners off by 6.3 degrees; the narrower windows agree with each
    # other there and not with the widest, so the frames near the corners take a narrower one
    clean, heads, times = _smooth_motion(90)
    angle = (8.0 * (times - 1.0)).clamp(0.0, 1.2)
    kick = torch.zeros(90, len(PARENTS), 3, dtype=torch.float64)
    kick[:, 3, 0] = angle
    kicked = corrected_transforms(clean, heads, ancestor_jumps(PARENTS), kick, torch.zeros(90, 3, dtype=torch.float64))
    angles, _ = _errors(_smoothed(kicked, heads, times, window=DEFAULT_WINDOW), kicked, heads)
    assert angles.max() < 3.5 and angles.mean() < 0.1, (float(angles.max()), float(angles.mean()))
    # with noise, the same motion is still averaged around the kick (the noise hides the corners)
    turns, offsets = _noise(90, degrees=5.0, metres=0.02, seed=1)
    noisy = corrected_transforms(kicked, heads, ancestor_jumps(PARENTS), turns, offsets)
    angles, _ = _errors(_smoothed(noisy, heads, times, window=DEFAULT_WINDOW), kicked, heads)
    assert angles[25:40, 3].mean() < 0.8 * 5.0 and angles.mean() < 0.6 * 5.0


def test_single_wild_frames_do_not_drag_their_neighbours():
    # every 11th frame is 40 degrees off per joint (an estimator's glitch): the robust passes give it no weight
    clean, heads, times = _smooth_motion(90)
    turns, offsets = _noise(90, degrees=5.0, metres=0.02, seed=2)
    turns[5::11] *= 8.0
    noisy = corrected_transforms(clean, heads, ancestor_jumps(PARENTS), turns, offsets)
    robust, _ = _errors(_smoothed(noisy, heads, times, window=DEFAULT_WINDOW), clean, heads)
    plain, _ = _errors(_smoothed(noisy, heads, times, window=DEFAULT_WINDOW, robust_passes=0), clean, heads)
    given, _ = _errors(noisy, clean, heads)
    assert robust.mean() < 0.65 * plain.mean(), (float(robust.mean()), float(plain.mean()))
    assert robust[5::11].mean() < 0.15 * given[5::11].mean()  # the wild frames themselves come back
    assert robust.mean() < 0.6 * 5.0


def test_frames_far_apart_in_time_are_not_averaged():
    clean, heads, times = _smooth_motion(40)
    turns, offsets = _noise(40, degrees=5.0, metres=0.02, seed=3)
    noisy = corrected_transforms(clean, heads, ancestor_jumps(PARENTS), turns, offsets)
    # frames 0.2 s apart: none within 0.15 s of another, so every frame keeps its own pose
    sparse = times * 6.0
    rotation, translation = smoothing_corrections(noisy, heads, PARENTS, sparse, window=0.15)
    assert rotation.abs().max() == 0 and translation.abs().max() == 0
    # a window of 0 is the given motion itself
    rotation, translation = smoothing_corrections(noisy, heads, PARENTS, times, window=0.0)
    assert rotation.abs().max() == 0 and translation.abs().max() == 0
    # two stretches 10 s apart are smoothed each on its own: the same result as smoothing each alone
    split = torch.cat([times[:20], times[20:] + 10.0])
    both = smoothing_corrections(noisy, heads, PARENTS, split, window=0.15, robust_passes=0)
    alone = smoothing_corrections(noisy[20:], heads, PARENTS, times[20:], window=0.15, robust_passes=0)
    assert torch.allclose(both[0][20:], alone[0], atol=1e-9) and torch.allclose(both[1][20:], alone[1], atol=1e-12)
    assert both[0][20:].abs().max() > 1e-3


def test_bad_smoothing_arguments_are_clear_errors():
    clean, heads, times = _smooth_motion(10)
    with pytest.raises(ValueError, match="window must be non-negative"):
        smoothing_corrections(clean, heads, PARENTS, times, window=-0.1)
    with pytest.raises(ValueError, match="strictly increasing"):
        smoothing_corrections(clean, heads, PARENTS, times.flip(0), window=0.15)
    with pytest.raises(ValueError, match="pose_prior_window"):
        preset("quick", refine_poses="on", pose_prior_window=-1.0)


def test_cli_rejects_a_negative_window_in_one_line(capsys):
    from warpavatar.cli.fit import main
    assert main(["--demo", "--pose-prior-window", "-0.5"]) == 2
    error = capsys.readouterr().err.strip()
    assert len(error.splitlines()) == 1 and "Traceback" not in error
    assert "pose_prior_window must be non-negative, got -0.5" in error


def test_the_fit_starts_at_the_smoothed_target(tmp_path):
    """On the demo subject perturbed per frame, the corrections start at the target (their mean over the training
    frames removed, the fit's gauge), which is closer to the exact poses than the given ones; the prior is zero."""
    perturb_folder(data.demo_subject_path() / "train", tmp_path / "train", rotation_deg=5.0, translation=0.03, seed=0)
    video = data.load_video_folder(tmp_path / "train", scale=0.5)
    exact = data.load_video_folder(data.demo_subject_path() / "train", scale=0.5)
    small = dict(iterations=1, image_scale=0.5, max_train_frames=25, init_points_per_bone=30,
                 init_carve_candidates=20000, init_carve_points=1500, max_gaussians=6000)
    trainer = Trainer(video, preset("quick", **small), tmp_path / "fit")
    extension = next(e for e in trainer.extensions if e.name == "pose_refinement")
    part = trainer.avatar.part("pose_refinement")
    assert torch.equal(part.rotation.detach(), extension.target_rotation)
    assert part.rotation.mean(0).abs().max() < 1e-6 and part.translation.mean(0).abs().max() < 1e-7
    assert part.rotation.detach().norm(dim=-1).mean() > math.radians(1.0)  # it did move the poses
    heads = torch.as_tensor(video.skeleton.heads, dtype=torch.float32)
    truth = posed_pivots(torch.as_tensor(exact.bone_transforms[trainer.frames.indices]).float(), heads)
    given = (posed_pivots(trainer.frames.bone_transforms.cpu(), heads) - truth).norm(dim=-1).mean()
    start = (posed_pivots(part.refined_poses().cpu(), heads) - truth).norm(dim=-1).mean()
    assert start < 0.9 * given, (float(start), float(given))
    # a window of 0: today's behaviour, corrections from zero
    still = Trainer(video, preset("quick", **small, pose_prior_window=0.0), tmp_path / "still")
    assert still.avatar.part("pose_refinement").rotation.abs().max() == 0
