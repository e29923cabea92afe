"""From a real video to a warpavatar video folder, offline: what ``warpavatar-prepare`` does, and its parts.

* :mod:`~warpavatar.prepare.calibration`: cameras, Qualisys ``.qca.txt`` and OpenCV-style TOML readers;
* :mod:`~warpavatar.prepare.triangulation`: confidence-weighted multi-view DLT, monocular root placement;
* :mod:`~warpavatar.prepare.skeleton_fit`: the 17-joint skeleton, its rest pose and per-frame bone transforms;
* :mod:`~warpavatar.prepare.smoothing`: confidence-gated zero-phase one-euro filtering;
* :mod:`~warpavatar.prepare.landmarks`: MediaPipe Pose (optional extra ``prepare``) and person masks;
* :mod:`~warpavatar.prepare.pipeline`: :func:`prepare_subject`, the steps above in order (its command line is
  :mod:`warpavatar.cli.prepare`).

Everything but the landmark detector works without MediaPipe installed.
"""

from warpavatar.prepare.calibration import CameraCalibration, read_calibration
from warpavatar.prepare.pipeline import prepare_subject
from warpavatar.prepare.skeleton_fit import SkeletonFit, fit_skeleton
from warpavatar.prepare.smoothing import one_euro_filter
from warpavatar.prepare.triangulation import triangulate_points

# the main entry points; each module's __all__ lists the rest
__all__ = ["prepare_subject", "CameraCalibration", "read_calibration", "triangulate_points", "SkeletonFit",
           "fit_skeleton", "one_euro_filter"]
