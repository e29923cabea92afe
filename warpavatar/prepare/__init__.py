"""From a real video to a warpavatar video folder, offline: ``warpavatar-prepare`` and its parts.

* :mod:`~warpavatar.prepare.calibration`: cameras, Qualisys ``.qca.txt`` and OpenCV-style TOML readers;
* :mod:`~warpavatar.prepare.triangulation`: confidence-weighted multi-view DLT, monocular root placement;
* :mod:`~warpavatar.prepare.skeleton_fit`: the 17-joint skeleton, its rest pose and per-frame bone transforms;
* :mod:`~warpavatar.prepare.smoothing`: confidence-gated zero-phase one-euro filtering;
* :mod:`~warpavatar.prepare.landmarks`: MediaPipe Pose (optional extra ``prepare``) and person masks;
* :mod:`~warpavatar.prepare.cli`: :func:`prepare_subject` and the console script.

Everything but the landmark detector works without MediaPipe installed.
"""

from warpavatar.prepare.calibration import CameraCalibration, match_cameras, read_calibration, read_qca, read_toml
from warpavatar.prepare.cli import prepare_subject
from warpavatar.prepare.skeleton_fit import (
    JOINT_NAMES,
    JOINT_PARENTS,
    LANDMARK_NAMES,
    BodyMeasurements,
    PoseSmoothing,
    RestModel,
    Skeleton,
    SkeletonFit,
    build_rest_skeleton,
    fit_skeleton,
    forward_kinematics,
    measure_body,
)
from warpavatar.prepare.smoothing import OneEuroSettings, one_euro_filter
from warpavatar.prepare.triangulation import TriangulationResult, solve_translation, triangulate_points

__all__ = [
    "CameraCalibration",
    "read_calibration",
    "read_qca",
    "read_toml",
    "match_cameras",
    "triangulate_points",
    "TriangulationResult",
    "solve_translation",
    "LANDMARK_NAMES",
    "JOINT_NAMES",
    "JOINT_PARENTS",
    "Skeleton",
    "BodyMeasurements",
    "RestModel",
    "PoseSmoothing",
    "SkeletonFit",
    "measure_body",
    "build_rest_skeleton",
    "fit_skeleton",
    "forward_kinematics",
    "OneEuroSettings",
    "one_euro_filter",
    "prepare_subject",
]
