"""Tests of warpavatar-prepare: calibration readers, triangulation, root placement, smoothing, skeleton fit, masks,
and the whole command on a few real frames (those need MediaPipe: skipped without it, except in CI).

Everything runs on CPU with numpy; the real-frame fixture (tests/data/pose2sim_clip) is six 270x480 frames of two
views of the Pose2Sim demo (BSD-3, see its LICENSE.txt).
"""

import json
import math
import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from warpavatar.prepare import calibration as calib
from warpavatar.prepare import skeleton_fit as sf
from warpavatar.prepare.landmarks import mediapipe_available, person_mask
from warpavatar.prepare.smoothing import OneEuroSettings, align_quaternion_signs, one_euro_filter, smooth_quaternions
from warpavatar.prepare.triangulation import correct_label_swaps, solve_translation, triangulate_points

CLIP = Path(__file__).parent / "data" / "pose2sim_clip"
SEEDS = (0, 1, 2)
# CI installs the prepare extra (.ci/run sets CI=true), so there a missing or broken MediaPipe fails these tests
# with its import error instead of skipping them.
needs_mediapipe = pytest.mark.skipif(not os.environ.get("CI") and not mediapipe_available(),
                                     reason="MediaPipe (extra 'prepare') not installed")


# ------------------------------------------------------------------------------------------------------------------
# Calibration readers.

QCA_TEXT = """<?xml version='1.0' encoding='ASCII'?>
<calibration type="regular">
  <cameras>
    <camera active="1" serial="camA" viewrotation="0">
      <fov_video bottom="599" left="10" right="1009" top="0"/>
      <transform r11="1" r12="0" r13="0" r21="0" r22="1" r23="0" r31="0" r32="0" r33="1" x="1000" y="2000" z="3000"/>
      <intrinsic centerPointU="32640" centerPointV="19200" focalLengthU="64000" focalLengthV="70400"
        radialDistortion1="-0.1" radialDistortion2="0.05" radialDistortion3="0.01" skew="0"
        tangentalDistortion1="0.001" tangentalDistortion2="-0.002"/>
    </camera>
    <camera active="1" serial="camB" viewrotation="0" video_resolution="720p">
      <fov_video bottom="1079" left="0" right="1919" top="0"/>
      <transform r11="0" r12="-1" r13="0" r21="1" r22="0" r23="0" r31="0" r32="0" r33="1" x="0" y="0" z="1000"/>
      <intrinsic centerPointU="61440" centerPointV="34560" focalLengthU="96000" focalLengthV="96000"
        radialDistortion1="0" radialDistortion2="0" radialDistortion3="0" skew="0"
        tangentalDistortion1="0" tangentalDistortion2="0"/>
    </camera>
  </cameras>
</calibration>
"""


def test_read_qca_hand_computed_values(tmp_path):
    path = tmp_path / "lab.qca.txt"
    path.write_text(QCA_TEXT)
    camera_a, camera_b = calib.read_calibration(path)
    # camA: K from 1/64-pixel units, the principal point shifted by the fov window's left edge (10 px).
    assert camera_a.name == "camA" and (camera_a.width, camera_a.height) == (1000, 600)
    np.testing.assert_allclose(camera_a.K, [[1000.0, 0, 500.0], [0, 1100.0, 300.0], [0, 0, 1]])
    np.testing.assert_allclose(camera_a.distortion, [-0.1, 0.05, 0.001, -0.002, 0.01])
    # Identity Qualisys rotation: OpenCV's camera is turned half a circle about x; t = -R C with C in metres.
    np.testing.assert_allclose(camera_a.rotation, np.diag([1.0, -1.0, -1.0]))
    np.testing.assert_allclose(camera_a.translation, [-1.0, 2.0, 3.0])
    np.testing.assert_allclose(camera_a.center, [1.0, 2.0, 3.0])
    # camB: 720p video of a 1080-line calibration scales K and the size by 2/3.
    assert (camera_b.width, camera_b.height) == (1280, 720)
    np.testing.assert_allclose(camera_b.K, [[1000.0, 0, 640.0], [0, 1000.0, 360.0], [0, 0, 1]])
    np.testing.assert_allclose(camera_b.rotation, [[0, -1, 0], [-1, 0, 0], [0, 0, -1]], atol=1e-12)
    np.testing.assert_allclose(camera_b.translation, [0.0, 0.0, 1.0], atol=1e-12)


def test_read_qca_demo_file_matches_pose2sim_conversion():
    # Pose2Sim's own converter turned this file's cam01 into (Calib_qualisys.toml of its demo):
    cameras = calib.read_qca(CLIP / "Calib.qca.txt")
    cam01 = cameras[0]
    assert [camera.name for camera in cameras] == ["cam01", "cam02", "cam03", "cam04"]
    assert (cam01.width, cam01.height) == (1088, 1920)
    np.testing.assert_allclose(cam01.K[0], [1681.244873046875, 0.0, 532.97369384375])
    np.testing.assert_allclose(cam01.K[1], [0.0, 1681.075439453125, 948.137390140625])
    rotation_vector = cv2.Rodrigues(cam01.rotation)[0].ravel()
    expected_rotation = [1.6882754799999993, 1.0483220499999997, -0.41955852000000016]
    expected_translation = [0.3211048899999996, 0.9563320600000009, 2.8907130499999996]
    np.testing.assert_allclose(rotation_vector, expected_rotation, atol=1e-8)
    np.testing.assert_allclose(cam01.translation, expected_translation, atol=1e-8)


TOML_TEXT = """
[cam_01]
name = "cam_01"
size = [ 640.0, 480.0]
matrix = [ [ 500.0, 0.0, 319.5], [ 0.0, 510.0, 239.5], [ 0.0, 0.0, 1.0]]
distortions = [ -0.2, 0.1, 0.001, 0.002]
rotation = [ 0.0, 0.0, 1.5707963267948966]
translation = [ 1.0, 2.0, 3.0]
fisheye = false

[cam_02]
size = [ 100.0, 50.0]
matrix = [ [ 80.0, 0.0, 49.5], [ 0.0, 80.0, 24.5], [ 0.0, 0.0, 1.0]]
distortions = [ 0.01, 0.002, 0.0, 0.0]
rotation = [ 3.141592653589793, 0.0, 0.0]
translation = [ 0.0, 0.0, 2.0]
fisheye = true

[metadata]
adjusted = false
error = 0.0
"""


def test_read_toml_hand_computed_values(tmp_path):
    path = tmp_path / "Calib.toml"
    path.write_text(TOML_TEXT)
    first, second = calib.read_calibration(path)
    assert first.name == "cam_01" and (first.width, first.height) == (640, 480) and not first.fisheye
    np.testing.assert_allclose(first.K, [[500.0, 0, 319.5], [0, 510.0, 239.5], [0, 0, 1]])
    np.testing.assert_allclose(first.distortion, [-0.2, 0.1, 0.001, 0.002, 0.0])
    # Rodrigues (0, 0, pi/2): a quarter turn about z.
    np.testing.assert_allclose(first.rotation, [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(first.translation, [1.0, 2.0, 3.0])
    np.testing.assert_allclose(first.center, [-2.0, 1.0, -3.0], atol=1e-12)  # -R^T t
    # The table name stands in for a missing 'name'; (pi, 0, 0) is a half turn about x.
    assert second.name == "cam_02" and second.fisheye
    np.testing.assert_allclose(second.rotation, np.diag([1.0, -1.0, -1.0]), atol=1e-12)
    np.testing.assert_allclose(second.center, [0.0, 0.0, 2.0], atol=1e-12)


@pytest.mark.parametrize("name, text, match", [
    ("calib.yaml", "x: 1", "unknown calibration format"),
    ("empty.toml", "[metadata]\nerror = 0.0\n", "no camera table"),
    ("partial.toml", "[c]\nmatrix = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]\nsize = [10.0, 10.0]\n",
     "lacks rotation, translation"),
    ("broken.qca.txt", "<calibration><cameras>", "not a valid Qualisys"),
    ("short.qca.txt", '<calibration><cameras><camera serial="c"/></cameras></calibration>', "lacks"),
])
def test_unreadable_calibration_files_are_clear_errors(tmp_path, name, text, match):
    (tmp_path / name).write_text(text)
    with pytest.raises(ValueError, match=match):
        calib.read_calibration(tmp_path / name)


def test_calibration_errors(tmp_path):
    with pytest.raises(FileNotFoundError):
        calib.read_calibration(tmp_path / "missing.toml")
    with pytest.raises(ValueError, match="proper rotation"):
        calib.CameraCalibration("bad", 10, 10, np.eye(3), np.zeros(5), np.diag([1.0, 1.0, -1.0, 1.0]))


def test_match_cameras_by_name():
    cameras = [
        calib.CameraCalibration(name, 10, 10, np.eye(3), np.zeros(5), np.eye(4))
        for name in ("cam_01", "cam_02", "cam_10")
    ]
    chosen = calib.match_cameras(["cam02", "cam01", "walk_cam10"], cameras)
    assert [camera.name for camera in chosen] == ["cam_02", "cam_01", "cam_10"]
    with pytest.raises(ValueError, match="matches 0 calibrated cameras"):
        calib.match_cameras(["phone"], cameras)
    with pytest.raises(ValueError, match="same calibrated camera"):
        calib.match_cameras(["cam01", "cam_01"], cameras)


def _random_camera(rng, *, name="c", distortion=None, fisheye=False, distance=4.0):
    """A camera on a sphere around the origin looking at it, z up, with mild random intrinsics."""
    azimuth = rng.uniform(0, 2 * math.pi)
    centre = np.array([math.cos(azimuth), math.sin(azimuth), rng.uniform(0.1, 0.5)]) * distance
    forward = -centre / np.linalg.norm(centre)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    rotation = np.stack([right, down, forward])
    world_to_camera = np.eye(4)
    world_to_camera[:3, :3] = rotation
    world_to_camera[:3, 3] = -rotation @ centre
    focal = rng.uniform(700, 900)
    K = np.array([[focal, 0, 319.5 + rng.uniform(-5, 5)], [0, focal * rng.uniform(0.98, 1.02), 239.5], [0, 0, 1]])
    if distortion is None:
        distortion = np.zeros(5)
    return calib.CameraCalibration(name, 640, 480, K, distortion, world_to_camera, fisheye=fisheye)


@pytest.mark.parametrize("fisheye", [False, True])
def test_distortion_round_trip(fisheye):
    rng = np.random.default_rng(3)
    distortion = [0.05, -0.01, 0.002, -0.001] if fisheye else [-0.12, 0.05, 0.001, -0.002, 0.003]
    camera = _random_camera(rng, distortion=distortion, fisheye=fisheye)
    points = rng.normal(scale=0.5, size=(50, 3))
    raw = camera.project(points)
    ideal = camera.project(points, distort=False)
    assert np.abs(raw - ideal).max() > 0.5  # the distortion does something
    np.testing.assert_allclose(camera.undistort_pixels(raw), ideal, atol=1e-6)
    assert np.isnan(camera.project(camera.center + camera.rotation[2] * -1.0)).all()  # behind the camera


def test_resized_camera_follows_pixel_centres():
    camera = calib.CameraCalibration("c", 640, 480, [[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]],
                                      np.zeros(5), np.eye(4))
    half = camera.resized(320, 240)
    np.testing.assert_allclose(half.K, [[250.0, 0, 159.5], [0, 250.0, 119.5], [0, 0, 1]])
    point = np.array([0.3, -0.2, 2.0])
    u_full = camera.project(point)
    np.testing.assert_allclose(half.project(point), (u_full + 0.5) * 0.5 - 0.5)


# ------------------------------------------------------------------------------------------------------------------
# Triangulation and root placement.


@pytest.mark.parametrize("seed", SEEDS)
def test_triangulation_recovers_points_with_distortion_and_an_outlier_view(seed):
    rng = np.random.default_rng(seed)
    cameras = [
        _random_camera(rng, name=f"c{index}", distortion=[-0.1, 0.03, 0.001, 0.0005, 0.0]) for index in range(4)
    ]
    points = rng.normal(scale=0.4, size=(7, 5, 3)) + [0, 0, 1.0]
    pixels = np.stack([camera.project(points) for camera in cameras])
    confidence = rng.uniform(0.5, 1.0, size=pixels.shape[:-1])
    # View 3 saw someone else for point [0, 0]; view 2 missed point [1, 1]; point [2, 2] is seen by one view only.
    pixels[3, 0, 0] += [80.0, -60.0]
    pixels[2, 1, 1] = np.nan
    confidence[1:, 2, 2] = 0.0
    result = triangulate_points(pixels, confidence, cameras, outlier_threshold_px=5.0)
    assert result.points.shape == (7, 5, 3) and result.confidence.shape == (7, 5)
    assert result.reprojection_error_px.shape == (4, 7, 5)
    valid = np.ones((7, 5), bool)
    valid[2, 2] = False
    np.testing.assert_allclose(result.points[valid], points[valid], atol=1e-6)
    assert np.isnan(result.points[2, 2]).all() and result.confidence[2, 2] == 0
    assert not result.inlier_views[3, 0, 0] and result.inlier_views[:3, 0, 0].all()
    assert (result.confidence[valid] >= 0.5).all()
    # Without the outlier test the wrong view drags the point.
    dragged = triangulate_points(pixels, confidence, cameras, outlier_threshold_px=None)
    assert np.linalg.norm(dragged.points[0, 0] - points[0, 0]) > 1e-3


def test_triangulation_weights_follow_confidence():
    rng = np.random.default_rng(5)
    cameras = [_random_camera(rng, name=f"c{index}") for index in range(3)]
    point = np.array([[0.1, -0.2, 1.1]])
    pixels = np.stack([camera.project(point) for camera in cameras])
    pixels[0] += 4.0  # a noisy view
    low = triangulate_points(pixels, np.array([[0.15], [1.0], [1.0]]), cameras, outlier_threshold_px=None)
    high = triangulate_points(pixels, np.array([[1.0], [1.0], [1.0]]), cameras, outlier_threshold_px=None)
    assert np.linalg.norm(low.points - point) < 0.5 * np.linalg.norm(high.points - point)


def test_label_swaps_are_undone_from_the_other_views():
    rng = np.random.default_rng(7)
    cameras = [_random_camera(rng, name=f"c{index}") for index in range(4)]
    rest = sf.build_rest_skeleton(BODY)
    _, _, landmarks = _synthetic_sequence(rest, 5, rng)
    landmarks = landmarks - landmarks.mean(axis=(0, 1)) + [0, 0, 1.0]  # in front of every camera
    pixels = np.stack([camera.project(landmarks) for camera in cameras])
    confidence = np.ones(pixels.shape[:-1])
    arms, legs = sf.mirrored_landmark_order(part="arms"), sf.mirrored_landmark_order(part="legs")
    swapped = pixels.copy()
    swapped[1, 2] = pixels[1, 2, arms]  # view 1 calls the left arm right in frame 2
    swapped[3, 4] = pixels[3, 4, legs]  # view 3 swaps the legs in frame 4
    fixed, fixed_confidence, relabeled = correct_label_swaps(
        swapped, confidence, cameras, [arms, legs], min_error_px=2.0, outlier_threshold_px=5.0,
    )
    np.testing.assert_allclose(fixed, pixels, atol=1e-9)
    expected = np.zeros((4, 5, 2), bool)
    expected[1, 2, 0] = expected[3, 4, 1] = True
    np.testing.assert_array_equal(relabeled, expected)
    result = triangulate_points(fixed, fixed_confidence, cameras)
    np.testing.assert_allclose(result.points, landmarks, atol=1e-6)
    # Two views cannot tell which one is wrong: nothing changes.
    unchanged, _, none = correct_label_swaps(swapped[:2], confidence[:2], cameras[:2], [arms, legs])
    np.testing.assert_array_equal(unchanged, swapped[:2])
    assert not none.any()
    with pytest.raises(ValueError, match="self-inverse"):
        correct_label_swaps(swapped, confidence, cameras, [np.roll(np.arange(33), 1)])


def test_mirrored_landmark_order():
    for part, pair_count in (("all", 16), ("face", 5), ("arms", 6), ("legs", 5)):
        order = sf.mirrored_landmark_order(part=part)
        np.testing.assert_array_equal(order[order], np.arange(33))  # its own inverse
        assert (order != np.arange(33)).sum() == 2 * pair_count
        for index, partner in enumerate(order):
            name, other = sf.LANDMARK_NAMES[index], sf.LANDMARK_NAMES[partner]
            assert other == name or other == name.replace("left", "right") or name == other.replace("left", "right")
    with pytest.raises(ValueError, match="part must be"):
        sf.mirrored_landmark_order(part="hands")


def test_triangulation_errors():
    rng = np.random.default_rng(0)
    cameras = [_random_camera(rng) for _ in range(2)]
    with pytest.raises(ValueError, match="at least two cameras"):
        triangulate_points(np.zeros((1, 4, 2)), np.ones((1, 4)), cameras[:1])
    with pytest.raises(ValueError, match="pixels must have shape"):
        triangulate_points(np.zeros((3, 4, 2)), np.ones((3, 4)), cameras)
    with pytest.raises(ValueError, match="confidence must have shape"):
        triangulate_points(np.zeros((2, 4, 2)), np.ones((2, 5)), cameras)
    empty = triangulate_points(np.zeros((2, 0, 2)), np.ones((2, 0)), cameras)
    assert empty.points.shape == (0, 3)


@pytest.mark.parametrize("seed", SEEDS)
def test_solve_translation_recovers_root(seed):
    rng = np.random.default_rng(seed)
    K = np.array([[900.0, 0, 300.0], [0, 905.0, 500.0], [0, 0, 1]])
    relative = rng.normal(scale=0.4, size=(6, 33, 3))
    truth = np.stack([rng.uniform(-0.5, 0.5, 6), rng.uniform(-0.5, 0.5, 6), rng.uniform(3, 6, 6)], -1)
    camera_points = relative + truth[:, None]
    pixels = camera_points[..., :2] / camera_points[..., 2:] * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]
    confidence = rng.uniform(0.5, 1, size=(6, 33))
    confidence[5] = 0.0  # a frame without a person
    pixels[4, :30] = np.nan  # a frame with 3 points
    solved = solve_translation(relative, pixels, confidence, K)
    np.testing.assert_allclose(solved[:5], truth[:5], atol=1e-8)
    assert np.isnan(solved[5]).all()


# ------------------------------------------------------------------------------------------------------------------
# Smoothing.


def test_one_euro_removes_jitter_and_keeps_motion():
    rng = np.random.default_rng(0)
    rate = 60.0
    time = np.arange(240) / rate
    motion = np.stack([0.2 * np.sin(2 * math.pi * 0.4 * time), 0.3 * time, np.zeros_like(time)], -1)[:, None]
    noisy = motion + rng.normal(scale=0.005, size=motion.shape)
    smoothed = one_euro_filter(noisy, rate_hz=rate, settings=OneEuroSettings(min_cutoff_hz=1.5, beta=2.0))
    inner = slice(10, -10)
    raw_error = np.abs(noisy - motion)[inner].mean()
    smooth_error = np.abs(smoothed - motion)[inner].mean()
    assert smooth_error < 0.5 * raw_error
    # Jitter (second differences) drops a lot; the zero-phase filter has no systematic lag on the ramp.
    assert np.abs(np.diff(smoothed, 2, axis=0)).mean() < 0.3 * np.abs(np.diff(noisy, 2, axis=0)).mean()
    assert abs((smoothed - motion)[inner, 0, 1].mean()) < 1e-3
    causal_settings = OneEuroSettings(min_cutoff_hz=1.5, beta=2.0, zero_phase=False)
    causal = one_euro_filter(noisy, rate_hz=rate, settings=causal_settings)
    assert (causal - motion)[inner, 0, 1].mean() < -1e-3  # a causal filter lags behind the ramp


def test_one_euro_confidence_gate_ignores_untrusted_samples():
    signal = np.zeros((50, 1, 3))
    signal[20:23] = 1.0  # a jump the detector was not sure of
    confidence = np.ones((50, 1))
    confidence[20:23] = 0.0
    gated = one_euro_filter(signal, rate_hz=30.0, confidence=confidence)
    trusted = one_euro_filter(signal, rate_hz=30.0)
    assert np.abs(gated).max() < 1e-12
    assert np.abs(trusted).max() > 0.1
    with pytest.raises(ValueError, match="finite"):
        one_euro_filter(np.full((3, 1, 1), np.nan), rate_hz=30.0)
    with pytest.raises(ValueError, match="shape"):
        one_euro_filter(np.zeros((3, 1)), rate_hz=30.0)
    with pytest.raises(ValueError, match="min_cutoff_hz"):
        OneEuroSettings(min_cutoff_hz=0.0)


def test_quaternion_smoothing_handles_sign_flips():
    angles = np.linspace(0, 1.0, 30)
    quaternions = np.stack([np.cos(angles / 2), np.sin(angles / 2), 0 * angles, 0 * angles], -1)[:, None]
    flipped = quaternions.copy()
    flipped[::2] *= -1.0  # the same rotations, alternating signs
    aligned = align_quaternion_signs(flipped)
    assert (np.sum(aligned[1:] * aligned[:-1], axis=-1) > 0).all()
    smoothed = smooth_quaternions(flipped, rate_hz=30.0)
    np.testing.assert_allclose(np.linalg.norm(smoothed, axis=-1), 1.0, atol=1e-12)
    assert np.abs(np.abs(np.sum(smoothed * quaternions, axis=-1)) - 1).max() < 1e-3


# ------------------------------------------------------------------------------------------------------------------
# Skeleton fit on synthetic poses.

BODY = sf.BodyMeasurements(
    torso_length=0.5, neck_length=0.2, hip_width=0.25, shoulder_width=0.36, upper_arm=0.29, forearm=0.26, hand=0.08,
    hand_width=0.07, thigh=0.43, shin=0.41, foot=0.17, ear_width=0.15, nose_offset=0.1, nose_angle_rad=1.75,
)


def _axis_angle(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    cross = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(angle) * cross + (1 - math.cos(angle)) * cross @ cross


def _frame(primary, secondary, rest_primary, rest_secondary):
    def basis(first, second):
        first = first / np.linalg.norm(first)
        second = second - second.dot(first) * first
        second = second / np.linalg.norm(second)
        return np.stack([first, second, np.cross(first, second)], axis=1)

    return basis(primary, secondary) @ basis(rest_primary, rest_secondary).T


def _perpendicular_turn(rng, direction, max_angle):
    axis = rng.normal(size=3)
    axis -= axis.dot(direction) * direction / direction.dot(direction)
    return _axis_angle(axis, rng.uniform(0, max_angle))


def _synthetic_sequence(rest, frame_count, rng):
    """Random poses the landmarks determine completely, their bone transforms and their 33 landmarks.

    The torso is straight (spine and chest aim the same way; the spine's twist is midway between the hip and
    shoulder lines), elbows bend forward and knees backward by 40 to 120 degrees (so the bend fixes the limb's
    twist), and forearms, hands, shins, feet and the neck turn by pure swings, as the fit assumes.
    """
    skeleton = rest.skeleton
    index = {name: joint for joint, name in enumerate(skeleton.names)}
    x_axis, y_axis, z_axis = np.eye(3)
    world = np.zeros((frame_count, skeleton.joint_count, 3, 3))
    for frame in range(frame_count):
        chest = _axis_angle(z_axis, rng.uniform(0, 2 * math.pi)) @ _axis_angle(rng.normal(size=3), rng.uniform(0, 0.5))
        hip_line = chest @ _axis_angle(z_axis, rng.uniform(-0.5, 0.5)) @ x_axis
        torso = chest @ z_axis
        turns = {"chest": chest, "pelvis": _frame(hip_line, torso, x_axis, z_axis),
                 "spine": _frame(torso, hip_line + chest @ x_axis, z_axis, x_axis)}
        turns["neck"] = chest @ _perpendicular_turn(rng, z_axis, 0.5)
        turns["head"] = turns["neck"] @ _axis_angle(rng.normal(size=3), rng.uniform(0, 0.7))
        for side in ("left", "right"):
            arm = skeleton.tails[index[f"{side}_shoulder"]] - skeleton.heads[index[f"{side}_shoulder"]]
            arm /= np.linalg.norm(arm)
            turns[f"{side}_shoulder"] = chest @ _axis_angle(rng.normal(size=3), rng.uniform(0, 1.2))
            elbow_bend = _axis_angle(np.cross(arm, -y_axis), rng.uniform(0.7, 2.1))  # forward
            turns[f"{side}_elbow"] = turns[f"{side}_shoulder"] @ elbow_bend
            turns[f"{side}_wrist"] = turns[f"{side}_elbow"] @ _perpendicular_turn(rng, arm, 0.7)
            turns[f"{side}_hip"] = turns["pelvis"] @ _axis_angle(rng.normal(size=3), rng.uniform(0, 0.9))
            turns[f"{side}_knee"] = turns[f"{side}_hip"] @ _axis_angle(np.cross(-z_axis, y_axis), rng.uniform(0.7, 2.0))
            foot = skeleton.tails[index[f"{side}_ankle"]] - skeleton.heads[index[f"{side}_ankle"]]
            turns[f"{side}_ankle"] = turns[f"{side}_knee"] @ _perpendicular_turn(rng, foot, 0.5)
        for name, rotation in turns.items():
            world[frame, index[name]] = rotation
    local = world.copy()
    for joint, parent in enumerate(skeleton.parents):
        if parent >= 0:
            local[:, joint] = np.swapaxes(world[:, parent], -1, -2) @ world[:, joint]
    roots = rng.normal(scale=0.5, size=(frame_count, 3)) + [0, 0, 1.0]
    transforms, positions = sf.forward_kinematics(skeleton, local, roots)
    modelled = rest.landmark_joints >= 0
    landmarks = np.empty((frame_count, 33, 3))
    rest_points = np.concatenate([rest.landmarks[modelled], np.ones((modelled.sum(), 1))], axis=-1)
    carried = transforms[:, rest.landmark_joints[modelled]]
    landmarks[:, modelled] = np.einsum("tlab,lb->tla", carried, rest_points)[..., :3]
    landmarks[:, ~modelled] = positions[:, None, index["head"]]  # eyes, mouth...: unused, any finite value
    return transforms, positions, landmarks


def _lbs(transforms, points):
    # transforms [T, J, 4, 4], points [J, P, 3] attached to each joint -> [T, J, P, 3]
    homogeneous = np.concatenate([points, np.ones(points.shape[:-1] + (1,))], axis=-1)
    return np.einsum("tjab,jpb->tjpa", transforms, homogeneous)[..., :3]


@pytest.mark.parametrize("seed", SEEDS)
def test_skeleton_fit_reproduces_synthetic_bone_transforms(seed):
    rng = np.random.default_rng(seed)
    rest = sf.build_rest_skeleton(BODY)
    truth, positions, landmarks = _synthetic_sequence(rest, 12, rng)
    confidence = np.ones((12, 33))
    fit = sf.fit_skeleton(landmarks, confidence, smoothing=None, body=BODY)
    np.testing.assert_allclose(fit.skeleton.heads, rest.skeleton.heads, atol=1e-12)
    attached = rest.skeleton.heads[:, None] + rng.normal(scale=0.15, size=(rest.skeleton.joint_count, 40, 3))
    np.testing.assert_allclose(_lbs(fit.bone_transforms, attached), _lbs(truth, attached), atol=1e-4)
    np.testing.assert_allclose(fit.joint_positions, positions, atol=1e-6)


@pytest.mark.parametrize("seed", SEEDS)
def test_measure_body_recovers_symmetric_lengths(seed):
    rng = np.random.default_rng(seed)
    rest = sf.build_rest_skeleton(BODY)
    _, _, landmarks = _synthetic_sequence(rest, 9, rng)
    confidence = rng.uniform(0.6, 1.0, size=(9, 33))
    # Disturb the left forearm in a few low-confidence frames: the weighted median ignores them.
    landmarks[:3, sf.LANDMARK_NAMES.index("left_wrist")] += 0.2
    confidence[:3, sf.LANDMARK_NAMES.index("left_wrist")] = 0.1
    measured = sf.measure_body(landmarks, confidence)
    for name in ("torso_length", "neck_length", "hip_width", "shoulder_width", "upper_arm", "forearm", "hand",
                 "hand_width", "thigh", "shin", "foot", "ear_width", "nose_offset"):
        assert getattr(measured, name) == pytest.approx(getattr(BODY, name), abs=1e-9), name


def test_rest_skeleton_conventions():
    rest = sf.build_rest_skeleton(BODY)
    skeleton = rest.skeleton
    index = {name: joint for joint, name in enumerate(skeleton.names)}
    assert skeleton.joint_count == 17 and skeleton.parents[0] == -1
    assert all(parent < joint for joint, parent in enumerate(skeleton.parents))
    assert min(skeleton.heads[:, 2].min(), skeleton.tails[:, 2].min()) == pytest.approx(0.0, abs=1e-12)
    np.testing.assert_allclose(skeleton.heads[0, :2], 0.0, atol=1e-12)
    assert skeleton.heads[index["left_shoulder"], 0] > 0 > skeleton.heads[index["right_shoulder"], 0]  # left = +x
    assert skeleton.tails[index["left_ankle"], 1] < skeleton.heads[index["left_ankle"], 1]  # feet point to -y
    for joint, parent in enumerate(skeleton.parents):  # main children start at their parent's tail
        if parent >= 0 and skeleton.names[joint] not in {"left_shoulder", "right_shoulder", "left_hip", "right_hip"}:
            np.testing.assert_allclose(skeleton.heads[joint], skeleton.tails[parent], atol=1e-12)
    lengths = np.linalg.norm(skeleton.tails - skeleton.heads, axis=-1)
    assert lengths[index["left_elbow"]] == pytest.approx(BODY.forearm)
    assert lengths[index["right_knee"]] == pytest.approx(BODY.shin)
    document = skeleton.to_json_dict(decimals=6)
    assert document["format"] == "warpavatar-skeleton/1" and len(document["joints"]) == 17
    json.dumps(document)


def _check_rigid_and_chained(fit):
    rotations = fit.bone_transforms[..., :3, :3]
    identity = np.broadcast_to(np.eye(3), rotations.shape)
    np.testing.assert_allclose(np.swapaxes(rotations, -1, -2) @ rotations, identity, atol=1e-9)
    np.testing.assert_allclose(np.linalg.det(rotations), 1.0, atol=1e-9)
    last_rows = fit.bone_transforms[..., 3, :]
    np.testing.assert_allclose(last_rows, np.broadcast_to([0, 0, 0, 1.0], last_rows.shape))
    heads = fit.skeleton.heads
    # Each joint's transform takes its rest head to its posed head, and so does its parent's (rigid attachment).
    np.testing.assert_allclose(_lbs(fit.bone_transforms, heads[:, None])[:, :, 0], fit.joint_positions, atol=1e-9)
    for joint, parent in enumerate(fit.skeleton.parents):
        if parent >= 0:
            by_parent = fit.bone_transforms[:, parent, :3, :3] @ heads[joint] + fit.bone_transforms[:, parent, :3, 3]
            np.testing.assert_allclose(by_parent, fit.joint_positions[:, joint], atol=1e-9)


@pytest.mark.parametrize("seed", SEEDS)
def test_smoothed_fit_of_noisy_landmarks_is_rigid_and_less_jittery(seed):
    rng = np.random.default_rng(seed)
    rest = sf.build_rest_skeleton(BODY)
    _, _, keyframes = _synthetic_sequence(rest, 2, rng)
    # A smooth motion from one random pose to another over 2 s, plus detector noise and a few untrusted samples.
    weight = (0.5 - 0.5 * np.cos(np.linspace(0, math.pi, 60)))[:, None, None]
    smooth_motion = (1 - weight) * keyframes[0] + weight * keyframes[1]
    noisy = smooth_motion + rng.normal(scale=0.01, size=smooth_motion.shape)
    confidence = np.ones((60, 33))
    confidence[rng.integers(0, 60, 5), rng.integers(0, 33, 5)] = 0.05
    noisy[5, 15] = np.nan  # a missing landmark is interpolated
    smoothed = sf.fit_skeleton(noisy, confidence, fps=30.0, body=BODY)
    raw = sf.fit_skeleton(noisy, confidence, fps=30.0, body=BODY, smoothing=None)
    _check_rigid_and_chained(smoothed)
    _check_rigid_and_chained(raw)
    smoothed_jitter = sf.joint_jitter_mm(smoothed.joint_positions)["median"]
    assert smoothed_jitter < 0.5 * sf.joint_jitter_mm(raw.joint_positions)["median"]
    np.testing.assert_allclose(smoothed.raw_joint_positions, raw.joint_positions, atol=1e-9)


@pytest.mark.parametrize("seed", SEEDS)
def test_rays_pull_joints_onto_the_2d_landmarks(seed):
    rng = np.random.default_rng(seed)
    rest = sf.build_rest_skeleton(BODY)
    _, _, landmarks = _synthetic_sequence(rest, 6, rng)
    centre = np.array([0.0, -6.0, 1.0])
    # The 2D landmarks are exact; the 3D ones have depth errors along the viewing rays' orthogonal directions.
    rays = landmarks - centre
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    noisy = landmarks + rng.normal(scale=0.03, size=landmarks.shape)
    confidence = np.ones((6, 33))
    names = ["left_elbow", "left_wrist", "right_knee", "right_ankle"]
    joints = [sf.JOINT_NAMES.index(name) for name in ("left_elbow", "left_wrist", "right_knee", "right_ankle")]

    def angular_error(fit):
        # angle [rad] between each fitted joint's ray and its landmark's ray
        directions = fit.joint_positions[:, joints] - centre
        directions /= np.linalg.norm(directions, axis=-1, keepdims=True)
        target = rays[:, [sf.LANDMARK_NAMES.index(name) for name in names]]
        return np.arccos(np.clip(np.sum(directions * target, axis=-1), -1, 1))

    without = angular_error(sf.fit_skeleton(noisy, confidence, smoothing=None, body=BODY))
    fit_with_rays = sf.fit_skeleton(
        noisy, confidence, smoothing=None, body=BODY, ray_origins=centre, ray_directions=rays
    )
    with_rays = angular_error(fit_with_rays)
    # Exactly on the ray unless the bone's sphere misses it (its pivot is off by the noise): then closest to it.
    assert np.median(with_rays) < 1e-7 < 1e-3 < np.median(without)
    assert with_rays.mean() < 0.3 * without.mean()
    _check_rigid_and_chained(fit_with_rays)


def test_fit_skeleton_errors():
    with pytest.raises(ValueError, match=r"landmarks must have shape \[T, 33, 3\]"):
        sf.fit_skeleton(np.zeros((4, 32, 3)), np.ones((4, 32)))
    with pytest.raises(ValueError, match="confidence must have shape"):
        sf.fit_skeleton(np.zeros((4, 33, 3)), np.ones((4, 30)))
    with pytest.raises(ValueError, match="T = 0"):
        sf.fit_skeleton(np.zeros((0, 33, 3)), np.ones((0, 33)))
    with pytest.raises(ValueError, match="infinite"):
        sf.fit_skeleton(np.full((2, 33, 3), np.inf), np.ones((2, 33)))
    rest = sf.build_rest_skeleton(BODY)
    _, _, landmarks = _synthetic_sequence(rest, 2, np.random.default_rng(0))
    landmarks[:, sf.LANDMARK_NAMES.index("right_knee")] = np.nan
    with pytest.raises(ValueError, match="right_knee"):
        sf.fit_skeleton(landmarks, np.ones((2, 33)), body=BODY)
    with pytest.raises(ValueError, match="given together"):
        sf.fit_skeleton(np.zeros((2, 33, 3)), np.ones((2, 33)), body=BODY, ray_origins=np.zeros(3))
    with pytest.raises(ValueError, match="must be finite and positive"):
        sf.BodyMeasurements(**{**BODY.__dict__, "thigh": -1.0})


def test_person_mask_follows_the_tracked_person():
    segmentation = np.zeros((120, 160), np.float32)
    segmentation[10:110, 10:70] = 0.9  # a large bystander
    segmentation[30:100, 100:140] = 0.8  # the tracked person, smaller
    segmentation[5, 150] = 1.0  # a speck
    landmarks = np.array([[120.0, 40.0], [110.0, 80.0], [130.0, 95.0], [40.0, 50.0]])
    visibility = np.array([1.0, 0.9, 0.8, 0.1])  # the bystander's point is not visible
    mask = person_mask(segmentation, landmarks, visibility)
    assert mask.dtype == np.uint8 and set(np.unique(mask)) <= {0, 255}
    assert mask[60, 120] == 255 and mask[60, 40] == 0 and mask[5, 150] == 0
    # Without visible landmarks the largest component wins.
    fallback = person_mask(segmentation, landmarks, np.zeros(4))
    assert fallback[60, 40] == 255 and fallback[60, 120] == 0
    assert person_mask(np.zeros((8, 8)), landmarks, visibility).max() == 0
    with pytest.raises(ValueError, match="segmentation must have shape"):
        person_mask(np.zeros((2, 2, 2)), landmarks, visibility)


# ------------------------------------------------------------------------------------------------------------------
# The whole command on real frames.


def _validate_folder(folder: Path, *, expected_frames: int) -> dict:
    """Check a written video folder against docs/FORMAT.md (with warpavatar.data's loader when it is available)."""
    for name in ("cameras.json", "skeleton.json", "poses.npz", "meta.json", "landmarks.npz"):
        assert (folder / name).is_file(), name
    cameras = json.loads((folder / "cameras.json").read_text())
    skeleton = json.loads((folder / "skeleton.json").read_text())
    meta = json.loads((folder / "meta.json").read_text())
    assert meta["poses"] == "estimated"  # so that warpavatar-fit --refine-poses auto refines them
    poses = np.load(folder / "poses.npz")
    transforms = poses["bone_transforms"]
    frame_ids = poses["frame_ids"]
    assert transforms.dtype == np.float32 and frame_ids.dtype == np.int32
    assert transforms.shape == (expected_frames, len(skeleton["joints"]), 4, 4)
    rotations = transforms[..., :3, :3].astype(np.float64)
    identity = np.broadcast_to(np.eye(3), rotations.shape)
    np.testing.assert_allclose(np.swapaxes(rotations, -1, -2) @ rotations, identity, atol=1e-5)
    assert (np.linalg.det(rotations) > 0.999).all()
    for frame_id in frame_ids:
        image = cv2.imread(str(folder / "frames" / f"{frame_id:06d}.png"))
        mask = cv2.imread(str(folder / "masks" / f"{frame_id:06d}.png"), cv2.IMREAD_UNCHANGED)
        assert image.shape == (cameras["height"], cameras["width"], 3)
        assert mask.shape == image.shape[:2] and set(np.unique(mask)) <= {0, 255}
        assert 0.02 < (mask > 0).mean() < 0.5  # a person, not the whole frame
    assert len(list((folder / "frames").iterdir())) == expected_frames
    try:
        from warpavatar.data import load_video_folder
    except ImportError:
        load_video_folder = None
    if load_video_folder is not None:
        video = load_video_folder(folder)
        assert video.frame_count == expected_frames
    return meta


def _landmark_reprojection_px(folder: Path) -> np.ndarray:
    """Recompute the joints' reprojection errors from the written files alone."""
    cameras = json.loads((folder / "cameras.json").read_text())
    camera = calib.CameraCalibration("check", cameras["width"], cameras["height"], cameras["K"], np.zeros(5),
                                     cameras["world_to_camera"])
    poses = np.load(folder / "poses.npz")
    marks = np.load(folder / "landmarks.npz")
    pairs = [("left_elbow", "left_elbow"), ("right_knee", "right_knee"), ("left_wrist", "left_wrist"),
             ("right_ankle", "right_ankle"), ("left_shoulder", "left_shoulder"), ("right_hip", "right_hip")]
    errors = []
    for joint, landmark in pairs:
        projected = camera.project(poses["joint_positions"][:, sf.JOINT_NAMES.index(joint)].astype(np.float64))
        observed = marks["image_points"][:, sf.LANDMARK_NAMES.index(landmark)]
        seen = marks["visibility"][:, sf.LANDMARK_NAMES.index(landmark)] > 0.5
        errors.append(np.linalg.norm(projected - observed, axis=-1)[seen])
    return np.concatenate(errors)


@needs_mediapipe
def test_prepare_monocular_clip(tmp_path, capsys):
    from warpavatar.cli.prepare import main

    output = tmp_path / "mono"
    status = main([str(CLIP / "cam01.mp4"), "-o", str(output), "--quiet", "--max-size", "400", "--frames", "5",
                   "--license", str(CLIP / "LICENSE.txt")])
    assert status == 0, capsys.readouterr().err
    meta = _validate_folder(output / "train", expected_frames=5)
    assert (output / "LICENSE.txt").is_file() and not (output / "novel_view").exists()
    assert meta["prepare"]["mode"] == "monocular"
    cameras = json.loads((output / "train" / "cameras.json").read_text())
    assert (cameras["width"], cameras["height"]) == (225, 400)
    assert cameras["K"][0][0] == pytest.approx(26 / 36 * 400, rel=1e-3)  # the default field of view, resized
    # The fitted joints land within a few pixels of the 2D landmarks (frames are 400 pixels high).
    assert meta["reprojection_error_px"]["median"] < 4.0
    errors = _landmark_reprojection_px(output / "train")
    assert np.median(errors) < 4.0
    # The world is z-up with the feet near z = 0.
    poses = np.load(output / "train" / "poses.npz")
    ankles = poses["joint_positions"][:, [sf.JOINT_NAMES.index("left_ankle"), sf.JOINT_NAMES.index("right_ankle")]]
    head = poses["joint_positions"][:, sf.JOINT_NAMES.index("head")]
    assert (head[:, 2] > 1.2).all() and (np.abs(ankles[..., 2]) < 0.25).all()
    # Running again into the same folder needs --overwrite.
    assert main([str(CLIP / "cam01.mp4"), "-o", str(output), "--quiet", "--frames", "2"]) == 1
    assert "--overwrite" in capsys.readouterr().err


@needs_mediapipe
def test_prepare_calibrated_clip(tmp_path, capsys):
    from warpavatar.cli.prepare import main

    output = tmp_path / "multi"
    status = main([str(CLIP / "cam01.mp4"), str(CLIP / "cam02.mp4"), "--calibration", str(CLIP / "Calib.qca.txt"),
                   "-o", str(output), "--quiet", "--novel-view-stride", "2"])
    assert status == 0, capsys.readouterr().err
    train = _validate_folder(output / "train", expected_frames=6)
    novel = _validate_folder(output / "novel_view" / "cam02", expected_frames=3)
    assert train["prepare"]["mode"] == "multi-view"
    assert np.load(output / "novel_view" / "cam02" / "poses.npz")["frame_ids"].tolist() == [0, 2, 4]
    # Both views share one skeleton and the same poses at the same instants.
    skeleton_text = (output / "train" / "skeleton.json").read_text()
    assert skeleton_text == (output / "novel_view" / "cam02" / "skeleton.json").read_text()
    np.testing.assert_array_equal(np.load(output / "train" / "poses.npz")["bone_transforms"][::2],
                                  np.load(output / "novel_view" / "cam02" / "poses.npz")["bone_transforms"])
    # The calibrated camera, scaled to the 270x480 clip (1/4 of the calibration's 1088x1920).
    cameras = json.loads((output / "train" / "cameras.json").read_text())
    assert (cameras["width"], cameras["height"]) == (270, 480)
    assert cameras["K"][0][0] == pytest.approx(1681.244873046875 / 4, rel=1e-6)
    for meta, folder in ((train, output / "train"), (novel, output / "novel_view" / "cam02")):
        assert meta["reprojection_error_px"]["median"] < 4.0
        assert np.median(_landmark_reprojection_px(folder)) < 4.0
    try:
        from warpavatar.data import load_subject
    except ImportError:
        return
    subject = load_subject(output)
    assert subject.novel_view["cam02"].frame_count == 3


def test_prepare_argument_errors(tmp_path, capsys):
    from warpavatar.cli.prepare import main

    assert main([str(CLIP / "cam01.mp4"), str(CLIP / "cam02.mp4"), "-o", str(tmp_path / "x"), "--quiet"]) == 1
    assert "need --calibration" in capsys.readouterr().err
    assert main([str(tmp_path / "missing.mp4"), "-o", str(tmp_path / "x"), "--quiet"]) == 1
    assert "video not found" in capsys.readouterr().err
    assert main([str(CLIP / "cam01.mp4"), "-o", str(tmp_path / "x"), "--stride", "0", "--quiet"]) == 1
    assert "stride must be an integer >= 1" in capsys.readouterr().err
