"""What ``warpavatar-prepare`` does: a phone video (or several calibrated videos) made into a video folder, offline.

Monocular: ``prepare_subject(["clip.mp4"], "subject/")`` writes ``subject/train/``. Multi-view:
``prepare_subject(["cam01.mp4", "cam02.mp4", ...], "subject/", calibration="Calib.qca.txt")`` writes the first
video to ``subject/train/`` and every other one to ``subject/novel_view/<video name>/``, all sharing one skeleton
and one pose sequence in the calibration's world frame. The folder layout is docs/FORMAT.md's; docs/prepare.md
describes every step and its conventions. The command line around it is :mod:`warpavatar.cli.prepare`.
"""

from __future__ import annotations

import dataclasses
import math
import shutil
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from warpavatar.data.types import ESTIMATED_POSES
from warpavatar.data.writer import save_npz, staged_folder, write_json, write_png
from warpavatar.io.images import check_opencv_path
from warpavatar.prepare.calibration import CameraCalibration, match_cameras, read_calibration
from warpavatar.prepare.skeleton_fit import (
    JOINT_NAMES,
    LANDMARK_NAMES,
    PoseSmoothing,
    SkeletonFit,
    fit_skeleton,
    joint_jitter_mm,
    mirrored_landmark_order,
)
from warpavatar.prepare.triangulation import correct_label_swaps, solve_translation, triangulate_points

__all__ = ["prepare_subject", "default_focal_px", "reprojection_errors_px"]

# A phone's main camera is close to a 26 mm lens on a 36 mm wide full frame: 69 degrees across the long side.
DEFAULT_FOCAL_OVER_LONG_SIDE = 26.0 / 36.0
_PNG_COMPRESSION = 3  # zlib level of the frames and masks: many files, written fast
_REPROJECTION_MIN_VISIBILITY = 0.5
_L = {name: index for index, name in enumerate(LANDMARK_NAMES)}
# Joints whose pivot is a landmark (or the midpoint of two), for the reprojection error.
_JOINT_LANDMARKS = {
    "pelvis": ("left_hip", "right_hip"),
    "neck": ("left_shoulder", "right_shoulder"),
    "head": ("left_ear", "right_ear"),
    **{f"{side}_{part}": (f"{side}_{part}",) for side in ("left", "right")
       for part in ("shoulder", "elbow", "wrist", "hip", "knee", "ankle")},
}


def default_focal_px(width: int, height: int) -> float:
    """Focal length [px] assumed for an uncalibrated video: ``26/36`` of the long side (69 degrees across it)."""
    return DEFAULT_FOCAL_OVER_LONG_SIDE * max(width, height)


def reprojection_errors_px(
    joint_positions: np.ndarray, camera: CameraCalibration, image_points: np.ndarray, visibility: np.ndarray,
    *, min_visibility: float = _REPROJECTION_MIN_VISIBILITY,
) -> np.ndarray:
    """Distances [px] between projected joints and the 2D landmarks they stand for.

    Args:
        joint_positions: fitted joint heads [m], shape [T, J, 3] (J = the 17 joints of the prepare skeleton).
        camera: the camera (its undistorted image: the one the landmarks were found in).
        image_points: 2D landmarks [px], shape [T, 33, 2].
        visibility: their visibility, shape [T, 33].
        min_visibility: landmarks below it are not compared.

    Returns:
        The errors of every compared (frame, joint) pair, flat, float64.
    """
    projected = camera.project(joint_positions, distort=False)
    errors = []
    for joint_name, landmark_names in _JOINT_LANDMARKS.items():
        indices = [_L[name] for name in landmark_names]
        observed = image_points[:, indices].mean(axis=1)
        seen = visibility[:, indices].min(axis=1) >= min_visibility
        distance = np.linalg.norm(projected[:, JOINT_NAMES.index(joint_name)] - observed, axis=-1)
        errors.append(distance[seen & np.isfinite(distance)])
    return np.concatenate(errors) if errors else np.zeros(0)


def _error_summary(errors: np.ndarray) -> dict:
    if errors.size == 0:
        return {"median": None, "p90": None, "count": 0}
    return {"median": round(float(np.median(errors)), 3), "p90": round(float(np.percentile(errors, 90)), 3),
            "count": int(errors.size)}


class _VideoReader:
    """Frames of one video file, honouring its rotation metadata (OpenCV's automatic orientation)."""

    def __init__(self, path: Path):
        self.path = path
        check_opencv_path(path)  # a path that is not UTF-8 would crash OpenCV
        self.capture = cv2.VideoCapture(str(path))
        if not self.capture.isOpened():
            raise ValueError(f"cannot open video {path}")
        self.capture.set(cv2.CAP_PROP_ORIENTATION_AUTO, 1)
        self.fps = float(self.capture.get(cv2.CAP_PROP_FPS)) or 30.0
        self.rotation_deg = int(self.capture.get(cv2.CAP_PROP_ORIENTATION_META) or 0)
        self.frame_count = int(self.capture.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
        # The decoded (rotated) size, from a separate handle so this one stays at the first frame.
        probe = cv2.VideoCapture(str(path))
        probe.set(cv2.CAP_PROP_ORIENTATION_AUTO, 1)
        ok, frame = probe.read()
        probe.release()
        if not ok:
            raise ValueError(f"video {path} holds no readable frame")
        self.size = (int(frame.shape[1]), int(frame.shape[0]))

    def frames(self, start: int, stride: int, count: int | None):
        """Yield BGR frames ``start, start + stride, ...``, at most ``count`` of them."""
        for _ in range(start):
            if not self.capture.grab():
                return
        produced = 0
        while count is None or produced < count:
            ok, frame = self.capture.read()
            if not ok:
                return
            yield frame
            produced += 1
            for _ in range(stride - 1):
                if not self.capture.grab():
                    return

    def close(self):
        self.capture.release()


def _output_size(width: int, height: int, max_size: int) -> tuple[int, int]:
    scale = min(1.0, max_size / max(width, height))
    return max(1, int(round(width * scale))), max(1, int(round(height * scale)))


def _calibrated_camera_for_video(camera: CameraCalibration, width: int, height: int) -> CameraCalibration:
    """The calibrated camera for a video that may be a uniformly scaled (and a few pixels cropped) version."""
    scale = max(width, height) / max(camera.width, camera.height)
    scaled_width, scaled_height = camera.width * scale, camera.height * scale
    if abs(scaled_width - width) > 0.02 * width + 1 or abs(scaled_height - height) > 0.02 * height + 1:
        raise ValueError(
            f"video frames are {width}x{height} but camera {camera.name!r} is calibrated for "
            f"{camera.width}x{camera.height} (not a uniform scaling of it; is the video rotated?)"
        )
    resized = camera.resized(int(round(scaled_width)), int(round(scaled_height)))
    if (resized.width, resized.height) != (width, height):
        print(
            f"warning: camera {camera.name}: video is {width}x{height}, calibration {resized.width}x{resized.height} "
            "after scaling; assuming the difference is cropped at the right/bottom edge", file=sys.stderr,
        )
    return dataclasses.replace(resized, width=width, height=height)


@dataclasses.dataclass
class _Track:
    """Landmarks of one video at output resolution (undistorted image)."""

    name: str
    camera: CameraCalibration  # pinhole camera of the written (undistorted) frames
    image_points: np.ndarray  # [T, 33, 2]
    visibility: np.ndarray  # [T, 33]
    world_points: np.ndarray  # [T, 33, 3]
    folder: Path
    written_frames: np.ndarray  # indices (0..T-1) whose frame and mask were written
    fps: float
    rotation_deg: int
    source: str
    triangulation_error: dict | None = None
    label_swaps: int | None = None  # frames whose left/right labels were corrected from the other views


def _track_video(
    reader: _VideoReader, camera_full: CameraCalibration, folder: Path, *, name: str, output_size,
    start: int, stride: int, frame_count: int | None, write_every: int, progress: bool,
) -> _Track:
    from warpavatar.prepare.landmarks import PoseTracker, person_mask

    camera = camera_full.resized(*output_size)
    maps = camera.undistortion_maps() if camera.has_distortion else None
    (folder / "frames").mkdir(parents=True, exist_ok=True)
    (folder / "masks").mkdir(parents=True, exist_ok=True)
    image_points, visibility, world_points, written = [], [], [], []
    iterator = reader.frames(start, stride, frame_count)
    if progress:
        from tqdm import tqdm

        iterator = tqdm(iterator, total=frame_count, desc=f"landmarks {name}", unit="frame", file=sys.stderr)
    with PoseTracker() as tracker:
        for index, frame in enumerate(iterator):
            if (frame.shape[1], frame.shape[0]) != (camera_full.width, camera_full.height):
                raise ValueError(f"{reader.path}: frame {index} changes size to {frame.shape[1]}x{frame.shape[0]}")
            if (frame.shape[1], frame.shape[0]) != output_size:
                frame = cv2.resize(frame, output_size, interpolation=cv2.INTER_AREA)
            if maps is not None:
                frame = cv2.remap(frame, maps[0], maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
            observation = tracker.process(cv2.cvtColor(frame, cv2.COLOR_BGR2RGB))
            image_points.append(observation.image_points)
            visibility.append(observation.visibility)
            world_points.append(observation.world_points)
            if index % write_every == 0:
                mask = person_mask(observation.segmentation, observation.image_points, observation.visibility)
                write_png(folder / "frames" / f"{index:06d}.png", frame, compression=_PNG_COMPRESSION)
                write_png(folder / "masks" / f"{index:06d}.png", mask, compression=_PNG_COMPRESSION)
                written.append(index)
    if not image_points:
        raise ValueError(f"{reader.path}: no frame in the requested range (start {start}, stride {stride})")
    return _Track(
        name=name, camera=camera.without_distortion(), image_points=np.stack(image_points),
        visibility=np.stack(visibility), world_points=np.stack(world_points), folder=folder,
        written_frames=np.asarray(written, dtype=np.int64), fps=reader.fps / stride,
        rotation_deg=reader.rotation_deg, source=reader.path.name,
    )


def _fill_over_time(values: np.ndarray) -> np.ndarray:
    """Linear interpolation over frames of rows that are NaN; values has shape [T, C]."""
    frames = np.arange(values.shape[0])
    valid = np.isfinite(values).all(axis=-1)
    if not valid.any():
        raise ValueError("no person was found in any frame")
    return np.stack([np.interp(frames, frames[valid], values[valid, axis]) for axis in range(values.shape[1])], -1)


def _monocular_landmarks(track: _Track):
    """Metric landmarks in a z-up world frame for one video, plus that frame's camera and the landmarks' rays."""
    K = track.camera.K
    translation = solve_translation(track.world_points, track.image_points, track.visibility, K)
    translation = _fill_over_time(translation)
    camera_points = track.world_points + translation[:, None, :]
    visible = track.visibility >= _REPROJECTION_MIN_VISIBILITY
    # Up: the median torso direction; the floor: low percentile of the feet along it.
    mid_hip = 0.5 * (camera_points[:, _L["left_hip"]] + camera_points[:, _L["right_hip"]])
    mid_shoulder = 0.5 * (camera_points[:, _L["left_shoulder"]] + camera_points[:, _L["right_shoulder"]])
    torso = mid_shoulder - mid_hip
    torso = torso[np.isfinite(torso).all(axis=-1)]
    up = np.median(torso / np.linalg.norm(torso, axis=-1, keepdims=True), axis=0)
    up /= np.linalg.norm(up)
    feet = [_L[name] for name in ("left_heel", "right_heel", "left_foot_index", "right_foot_index")]
    foot_heights = (camera_points[:, feet] @ up)[visible[:, feet] & np.isfinite(camera_points[:, feet]).all(-1)]
    if foot_heights.size == 0:
        foot_heights = (camera_points[:, feet] @ up)[np.isfinite(camera_points[:, feet]).all(-1)]
    floor = float(np.percentile(foot_heights, 5))
    root = np.nanmedian(mid_hip, axis=0)
    origin = root - (root @ up - floor) * up
    x_axis = np.array([1.0, 0.0, 0.0]) - up[0] * up
    x_axis /= np.linalg.norm(x_axis)
    world_axes = np.stack([x_axis, np.cross(up, x_axis), up], axis=1)  # columns: world axes in camera frame
    world_to_camera = np.eye(4)
    world_to_camera[:3, :3] = world_axes
    world_to_camera[:3, 3] = origin
    camera = dataclasses.replace(track.camera, world_to_camera=world_to_camera)
    world_landmarks = (camera_points - origin) @ world_axes
    homogeneous = np.concatenate([track.image_points, np.ones(track.image_points.shape[:-1] + (1,))], axis=-1)
    directions = homogeneous @ np.linalg.inv(K).T
    directions = directions / np.linalg.norm(directions, axis=-1, keepdims=True)
    return world_landmarks, camera, camera.center, directions @ world_axes


def _write_folder(track: _Track, fit: SkeletonFit, *, meta: dict) -> dict:
    """cameras.json, skeleton.json, poses.npz, landmarks.npz and meta.json of one video folder."""
    rows = track.written_frames
    write_json(track.folder / "cameras.json", track.camera.to_cameras_json())
    write_json(track.folder / "skeleton.json", fit.skeleton.to_json_dict(decimals=6))
    save_npz(
        track.folder / "poses.npz",
        bone_transforms=fit.bone_transforms[rows].astype(np.float32),
        frame_ids=rows.astype(np.int32),
        joint_positions=fit.joint_positions[rows].astype(np.float32),
    )
    save_npz(
        track.folder / "landmarks.npz",
        image_points=track.image_points[rows].astype(np.float32),
        visibility=track.visibility[rows].astype(np.float32),
        frame_ids=rows.astype(np.int32),
        landmark_names=np.asarray(LANDMARK_NAMES),
    )
    errors = reprojection_errors_px(fit.joint_positions[rows], track.camera, track.image_points[rows],
                                    track.visibility[rows])
    meta = {
        "fps": round(track.fps, 6),
        "source": track.source,
        "camera": track.name,
        "poses": ESTIMATED_POSES,  # estimated from the images: --refine-poses auto refines them while fitting
        "frame_ids_step": int(rows[1] - rows[0]) if rows.size > 1 else 1,
        "video_rotation_deg": track.rotation_deg,
        "reprojection_error_px": _error_summary(errors),
        **meta,
    }
    write_json(track.folder / "meta.json", meta)
    return meta


def prepare_subject(
    videos: list,
    output,
    *,
    calibration=None,
    focal_px: float | None = None,
    max_size: int = 1024,
    start: int = 0,
    frame_count: int | None = None,
    stride: int = 1,
    novel_view_stride: int = 1,
    smoothing: PoseSmoothing | None = PoseSmoothing(),
    license_file=None,
    overwrite: bool = False,
    progress: bool = True,
) -> dict:
    """Make a subject folder (docs/FORMAT.md) from one video, or from several calibrated synchronized videos.

    Args:
        videos: video files; the first becomes ``train/``, the others (multi-view) ``novel_view/<stem>/``.
        output: the subject folder to create.
        calibration: ``.toml`` or Qualisys ``.qca.txt`` file; required with more than one video. Videos are
            matched to its cameras by name and may be uniformly scaled copies of the calibrated resolution.
        focal_px: monocular only: focal length in pixels of the original video (default: ``26/36`` of its
            long side, a phone's main camera).
        max_size: frames are resized so their long side is at most this many pixels (K follows).
        start: first source frame used.
        frame_count: number of frames used per video (default: all).
        stride: use every ``stride``-th source frame.
        novel_view_stride: write every n-th frame to the ``novel_view`` folders (all are still used to fit).
        smoothing: temporal smoothing of the fitted pose, or None.
        license_file: copied to ``output/LICENSE.txt`` when given.
        overwrite: replace an existing non-empty output folder.
        progress: show progress bars on stderr.

    Returns:
        The report also written to ``output/prepare_report.json``: per folder its meta.json, timings, settings.
        The folder is assembled under a temporary name beside it and renamed into place when complete.

    Raises:
        ValueError: bad options, unreadable videos, mismatched calibration, or no person found.
        MediaPipeUnavailableError: the ``prepare`` extra is not installed.
    """
    from warpavatar.prepare.landmarks import MEDIAPIPE_VERSION, require_mediapipe

    videos = [Path(video) for video in videos]
    output = Path(output)
    if not videos:
        raise ValueError("give at least one video")
    for video in videos:
        if not video.is_file():
            raise FileNotFoundError(f"video not found: {video}")
    if len(videos) > 1 and calibration is None:
        raise ValueError("several videos need --calibration (their cameras' intrinsics and poses)")
    if calibration is not None and focal_px is not None:
        raise ValueError("--focal-px is for uncalibrated (monocular) videos; the calibration gives K")
    if len({video.stem for video in videos}) != len(videos):
        raise ValueError("videos must have distinct file names (they name the novel_view folders)")
    for name, value, minimum in (("max_size", max_size, 16), ("stride", stride, 1),
                                 ("novel_view_stride", novel_view_stride, 1), ("start", start, 0)):
        if int(value) != value or value < minimum:
            raise ValueError(f"{name} must be an integer >= {minimum}, got {value}")
    if frame_count is not None and (int(frame_count) != frame_count or frame_count < 1):
        raise ValueError(f"frame_count must be a positive integer, got {frame_count}")
    if focal_px is not None and not (math.isfinite(focal_px) and focal_px > 0):
        raise ValueError(f"focal_px must be positive, got {focal_px}")
    require_mediapipe()
    if output.exists() and any(output.iterdir()) and not overwrite:
        raise ValueError(f"output folder {output} is not empty (pass --overwrite to replace it)")
    # Everything is written to a temporary folder and renamed into place once complete (an empty folder, or an
    # earlier output of this kind, is replaced; a folder warpavatar did not write is refused)
    with staged_folder(output, overwrite=True, overwrite_hint="--overwrite") as staging:
        timings = {}
        began = time.perf_counter()

        readers = [_VideoReader(video) for video in videos]
        try:
            sizes = [reader.size for reader in readers]
            if calibration is not None:
                calibrated = match_cameras([video.stem for video in videos], read_calibration(calibration))
                cameras = [_calibrated_camera_for_video(camera, *size) for camera, size in zip(calibrated, sizes)]
            else:
                width, height = sizes[0]
                focal = focal_px if focal_px is not None else default_focal_px(width, height)
                K = np.array([[focal, 0.0, (width - 1) / 2.0], [0.0, focal, (height - 1) / 2.0], [0.0, 0.0, 1.0]])
                cameras = [CameraCalibration(name=videos[0].stem, width=width, height=height, K=K,
                                             distortion=np.zeros(5), world_to_camera=np.eye(4))]
            if len(videos) > 1:
                available = [max(0, (reader.frame_count - start + stride - 1) // stride) for reader in readers]
                if min(available) > 0:
                    common = min(available)
                    frame_count = common if frame_count is None else min(frame_count, common)
            tracks = []
            for index, (reader, camera, size) in enumerate(zip(readers, cameras, sizes)):
                folder = staging / "train" if index == 0 else staging / "novel_view" / videos[index].stem
                tracks.append(_track_video(
                    reader, camera, folder, name=videos[index].stem, output_size=_output_size(*size, max_size),
                    start=start, stride=stride, frame_count=frame_count,
                    write_every=1 if index == 0 else novel_view_stride, progress=progress,
                ))
        finally:
            for reader in readers:
                reader.close()
        timings["landmarks_s"] = time.perf_counter() - began
        frame_total = min(track.image_points.shape[0] for track in tracks)
        if any(track.image_points.shape[0] != frame_total for track in tracks):
            # A container that announced more frames than it decodes: keep the instants every video has.
            counts = [track.image_points.shape[0] for track in tracks]
            print(f"warning: the videos decode {counts} frames; keeping the first {frame_total}", file=sys.stderr)
            for track in tracks:
                for index in track.written_frames[track.written_frames >= frame_total]:
                    (track.folder / "frames" / f"{index:06d}.png").unlink()
                    (track.folder / "masks" / f"{index:06d}.png").unlink()
                track.written_frames = track.written_frames[track.written_frames < frame_total]
                track.image_points = track.image_points[:frame_total]
                track.visibility = track.visibility[:frame_total]
                track.world_points = track.world_points[:frame_total]

        fit_began = time.perf_counter()
        fps = tracks[0].fps
        extra_meta = {}
        if len(tracks) == 1:
            track = tracks[0]
            if not np.isfinite(track.image_points).all(axis=(1, 2)).any():
                raise ValueError(f"no person was found in {track.source}")
            landmarks, camera, centre, directions = _monocular_landmarks(track)
            track.camera = camera
            fit = fit_skeleton(
                landmarks, track.visibility, fps=fps, smoothing=smoothing,
                ray_origins=centre, ray_directions=directions, ray_weights=track.visibility,
            )
            mode = "monocular"
            extra_meta["focal_px_source"] = "calibration" if calibration else ("--focal-px" if focal_px else "default")
        else:
            diagonal = float(np.hypot(tracks[0].camera.width, tracks[0].camera.height))
            options = {"undistort": False, "outlier_threshold_px": 0.02 * diagonal}
            cameras = [track.camera for track in tracks]
            # A view whose detector swapped left and right (whole body, arms or legs) is relabeled from the others.
            pixels, visibility, swaps = correct_label_swaps(
                np.stack([track.image_points for track in tracks]), np.stack([track.visibility for track in tracks]),
                cameras, [mirrored_landmark_order(part=part) for part in ("face", "arms", "legs")],
                min_error_px=0.01 * diagonal, **options,
            )
            for view, track in enumerate(tracks):
                track.image_points, track.visibility = pixels[view], visibility[view]
                track.label_swaps = int(swaps[view].any(axis=-1).sum())
            triangulated = triangulate_points(pixels, visibility, cameras, **options)
            if not (triangulated.confidence > 0).any():
                raise ValueError("no landmark could be triangulated (is the same person visible in two views?)")
            fit = fit_skeleton(triangulated.points, triangulated.confidence, fps=fps, smoothing=smoothing)
            mode = "multi-view"
            up = fit.joint_positions[:, JOINT_NAMES.index("neck")] - fit.joint_positions[:, 0]
            up_alignment = float(np.median(up[:, 2] / np.linalg.norm(up, axis=-1)))
            if up_alignment < 0.5:
                print(f"warning: the body's median up direction has z = {up_alignment:.2f} in the calibration's world: "
                      "docs/FORMAT.md expects a z-up world", file=sys.stderr)
            for view, track in enumerate(tracks):
                view_errors = triangulated.reprojection_error_px[view][triangulated.inlier_views[view]]
                track.triangulation_error = _error_summary(view_errors[np.isfinite(view_errors)])
        timings["fit_s"] = time.perf_counter() - fit_began

        jitter = {
            "unit": "mm per frame^2 (|p[t+1] - 2 p[t] + p[t-1]| of the joint heads)",
            "smoothed": {key: round(value, 3) for key, value in joint_jitter_mm(fit.joint_positions).items()},
            "raw_fit": {key: round(value, 3) for key, value in joint_jitter_mm(fit.raw_joint_positions).items()},
        }
        settings = {
            "mode": mode, "mediapipe": MEDIAPIPE_VERSION, "max_size": max_size, "start": start, "stride": stride,
            "frame_count": frame_total, "smoothing": dataclasses.asdict(smoothing) if smoothing else None,
            "calibration": Path(calibration).name if calibration else None,
        }
        body = {key: round(value, 4) for key, value in dataclasses.asdict(fit.rest.body).items()}
        report = {"mode": mode, "frames": frame_total, "fps": fps, "folders": {}, "jitter": jitter,
                  "body_measurements_m": body, "settings": settings}
        for track in tracks:
            meta = {"jitter": jitter, "prepare": settings, **extra_meta}
            if track.triangulation_error is not None:
                meta["triangulation_reprojection_error_px"] = track.triangulation_error
                meta["left_right_label_fixes"] = track.label_swaps
            relative = str(track.folder.relative_to(staging))
            report["folders"][relative] = _write_folder(track, fit, meta=meta)
        if license_file is not None:
            shutil.copyfile(license_file, staging / "LICENSE.txt")
        timings["total_s"] = time.perf_counter() - began
        report["timings"] = {key: round(value, 2) for key, value in timings.items()}
        write_json(staging / "prepare_report.json", report)
        return report
