"""Body landmarks and a person mask per video frame, with MediaPipe Pose (optional dependency), offline.

MediaPipe is optional (the ``prepare`` extra; docs/prepare.md gives an install that keeps numpy 2 and the
headless OpenCV). Only version 0.10.21 is supported: it bundles the full pose landmark model, the pose detector
and the segmentation head, and runs offline through the legacy ``solutions`` API with ``model_complexity=1``
(complexities 0 and 2 try to download their models, so they are not used).

Coordinates: image points are pixels with pixel centres at integer coordinates (MediaPipe's normalized
coordinates run over the image's edges, so a pixel coordinate is ``x * width - 0.5``). World points are
MediaPipe's metric landmarks [m]: origin between the hips, axes roughly those of the camera (x right, y down,
z away from the camera).
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np

__all__ = [
    "MEDIAPIPE_VERSION",
    "MediaPipeUnavailableError",
    "mediapipe_available",
    "require_mediapipe",
    "PoseObservation",
    "PoseTracker",
    "person_mask",
]

MEDIAPIPE_VERSION = "0.10.21"
_INSTALL_HINT = (
    "warpavatar-prepare needs MediaPipe 0.10.21 (its body landmark and segmentation models run offline). "
    "Install it without its numpy<2 and OpenCV pins: `pip install --no-deps mediapipe==0.10.21 && "
    "pip install absl-py attrs flatbuffers 'protobuf>=4.25.3,<5' matplotlib` (docs/prepare.md)."
)


class MediaPipeUnavailableError(ImportError):
    """MediaPipe (the ``prepare`` extra) is not installed or cannot be imported."""


def require_mediapipe():
    """Import MediaPipe's pose solution, or raise :class:`MediaPipeUnavailableError` with install instructions.

    Returns:
        The ``mediapipe.python.solutions.pose`` module.
    """
    try:
        from mediapipe.python.solutions import pose as mediapipe_pose
    except Exception as error:  # ImportError, or a binary extension failing to initialise
        raise MediaPipeUnavailableError(f"{_INSTALL_HINT} (import failed: {error})") from error
    return mediapipe_pose


def mediapipe_available() -> bool:
    """Whether :func:`require_mediapipe` succeeds."""
    try:
        require_mediapipe()
    except MediaPipeUnavailableError:
        return False
    return True


@dataclasses.dataclass(frozen=True)
class PoseObservation:
    """What the tracker sees in one frame.

    Attributes:
        image_points: 33 landmarks [px], shape [33, 2] float64 (NaN when no person was found).
        visibility: MediaPipe's visibility score of each landmark in [0, 1], shape [33] (0 when no person).
        world_points: 33 metric landmarks [m], shape [33, 3] float64, origin between the hips (NaN when none).
        segmentation: person probability per pixel in [0, 1], shape [H, W] float32 (zeros when none).
    """

    image_points: np.ndarray
    visibility: np.ndarray
    world_points: np.ndarray
    segmentation: np.ndarray

    @property
    def found(self) -> bool:
        """Whether a person was detected."""
        return bool(np.isfinite(self.image_points).all())


class PoseTracker:
    """MediaPipe Pose over the frames of one video, in order (it tracks one person from frame to frame).

    Use as a context manager, or call :meth:`close`.

    Args:
        min_detection_confidence: detector score needed to start tracking someone.
        min_tracking_confidence: landmark score under which the tracker re-runs the detector.
        smooth_landmarks: MediaPipe's own temporal filter on landmarks (the skeleton fit smooths as well).
    """

    def __init__(
        self,
        *,
        min_detection_confidence: float = 0.5,
        min_tracking_confidence: float = 0.5,
        smooth_landmarks: bool = True,
    ):
        mediapipe_pose = require_mediapipe()
        self._pose = mediapipe_pose.Pose(
            static_image_mode=False,
            model_complexity=1,
            smooth_landmarks=smooth_landmarks,
            enable_segmentation=True,
            smooth_segmentation=True,
            min_detection_confidence=min_detection_confidence,
            min_tracking_confidence=min_tracking_confidence,
        )

    def __enter__(self) -> "PoseTracker":
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def close(self) -> None:
        """Release MediaPipe's graph."""
        if self._pose is not None:
            self._pose.close()
            self._pose = None

    def process(self, image_rgb: np.ndarray) -> PoseObservation:
        """Landmarks and segmentation of the next frame.

        Args:
            image_rgb: the frame, shape [H, W, 3] uint8, RGB order.

        Returns:
            A :class:`PoseObservation`.
        """
        if self._pose is None:
            raise RuntimeError("PoseTracker is closed")
        if image_rgb.ndim != 3 or image_rgb.shape[2] != 3 or image_rgb.dtype != np.uint8:
            raise ValueError(f"image_rgb must be [H, W, 3] uint8, got {image_rgb.shape} {image_rgb.dtype}")
        height, width = image_rgb.shape[:2]
        result = self._pose.process(np.ascontiguousarray(image_rgb))
        if result.pose_landmarks is None or result.pose_world_landmarks is None:
            return PoseObservation(
                image_points=np.full((33, 2), np.nan), visibility=np.zeros(33),
                world_points=np.full((33, 3), np.nan), segmentation=np.zeros((height, width), np.float32),
            )
        normalized = np.array([[mark.x, mark.y, mark.visibility] for mark in result.pose_landmarks.landmark])
        world = np.array([[mark.x, mark.y, mark.z] for mark in result.pose_world_landmarks.landmark])
        segmentation = result.segmentation_mask
        if segmentation is None:
            segmentation = np.zeros((height, width), np.float32)
        return PoseObservation(
            image_points=np.stack([normalized[:, 0] * width - 0.5, normalized[:, 1] * height - 0.5], axis=-1),
            visibility=np.clip(normalized[:, 2], 0.0, 1.0),
            world_points=world,
            segmentation=np.asarray(segmentation, dtype=np.float32),
        )


def person_mask(
    segmentation: np.ndarray,
    image_points: np.ndarray,
    visibility: np.ndarray,
    *,
    threshold: float = 0.5,
    min_visibility: float = 0.5,
    kernel_fraction: float = 0.006,
) -> np.ndarray:
    """A clean binary mask of the tracked person.

    The probability map is thresholded, opened (removes specks) and closed (fills cracks) with an elliptic
    kernel, and of its connected components the one holding the most visible landmarks of the tracked person is
    kept (the largest when none holds any): with several people in view, the mask follows the tracked one.

    Args:
        segmentation: person probability, shape [H, W] float in [0, 1].
        image_points: the tracked person's landmarks [px], shape [N, 2] (NaN rows ignored).
        visibility: their visibility in [0, 1], shape [N].
        threshold: probability above which a pixel is the person.
        min_visibility: visibility a landmark needs to vote for a component.
        kernel_fraction: morphology kernel size as a fraction of the image diagonal (at least 3 pixels).

    Returns:
        The mask, shape [H, W] uint8, 255 = person, 0 = background.
    """
    segmentation = np.asarray(segmentation)
    if segmentation.ndim != 2:
        raise ValueError(f"segmentation must have shape [H, W], got {segmentation.shape}")
    image_points = np.asarray(image_points, dtype=np.float64).reshape(-1, 2)
    visibility = np.asarray(visibility, dtype=np.float64).reshape(-1)
    if visibility.shape[0] != image_points.shape[0]:
        raise ValueError(f"visibility must have {image_points.shape[0]} entries, got {visibility.shape[0]}")
    height, width = segmentation.shape
    binary = (segmentation > threshold).astype(np.uint8)
    size = max(3, int(round(kernel_fraction * float(np.hypot(height, width)))) | 1)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))
    binary = cv2.morphologyEx(binary, cv2.MORPH_OPEN, kernel)
    binary = cv2.morphologyEx(binary, cv2.MORPH_CLOSE, kernel)
    component_count, labels, stats, _ = cv2.connectedComponentsWithStats(binary, connectivity=8)
    if component_count <= 1:
        return np.zeros((height, width), np.uint8)
    votes = np.zeros(component_count)
    voters = np.isfinite(image_points).all(axis=-1) & (visibility >= min_visibility)
    for column, row in np.round(image_points[voters]).astype(np.int64):
        if 0 <= row < height and 0 <= column < width:
            votes[labels[row, column]] += 1
    votes[0] = -1  # background
    areas = stats[:, cv2.CC_STAT_AREA].astype(np.float64)
    areas[0] = -1
    best = int(np.lexsort((areas, votes))[-1])  # most votes, then largest
    return np.where(labels == best, 255, 0).astype(np.uint8)
