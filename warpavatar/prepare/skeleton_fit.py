"""A 17-joint skeleton fitted to MediaPipe's 33 body landmarks: bone lengths, rest pose, per-frame bone transforms.

The skeleton (docs/prepare.md has a figure-free description of every choice made here):

    pelvis (root) - spine - chest - neck - head
                            chest - {left,right}_shoulder - _elbow - _wrist
    pelvis - {left,right}_hip - _knee - _ankle

Each joint's bone runs from its head (pivot) to its tail: the shoulder joint carries the upper arm (shoulder to
elbow), the elbow the forearm, the wrist the hand, the hip the thigh, the knee the shin, the ankle the foot
(ankle to the toe tip), the head the skull (from between the ears upward).

Rest pose (world frame, z up, metres): the body stands upright facing -y, its left side toward +x, arms
hanging 45 degrees from the vertical in the frontal plane (an "A" pose), legs straight down, feet pointing
forward and 20 degrees downward, the lowest point on z = 0 and the pelvis above x = y = 0.

Per frame each joint gets a world rotation G_j (rest to posed) chosen in chain order:

* pelvis: the hip line (left hip - right hip) maps the rest x axis, the torso (mid-hip to mid-shoulder) sets
  the tilt about it;
* spine and chest: both aim from the spine's pivot at the mid-shoulder point; the chest's twist follows the
  shoulder line, the spine's the mean of the hip and shoulder lines;
* neck: the smallest rotation (a swing) from the chest's frame that aims it at the mid-ear point;
* head: the ear line and the nose direction;
* upper arm and thigh: aim at the elbow / knee; their twist puts the elbow's / knee's bend in its rest plane
  (elbows bend forward, knees backward), faded out toward a swing when the limb is nearly straight;
* forearm, hand, shin, foot: a swing from the parent's frame that aims at the wrist, hand centre, ankle, toe.

Every aim starts at the joint's pivot as placed by the chain so far, so errors do not accumulate along limbs,
and the positions come from forward kinematics with constant bone lengths: ``p_j = p_parent + G_parent (h_j -
h_parent)``. The bone transform is ``[G_j | p_j - G_j h_j]``, a proper rigid linear-blend-skinning matrix.
With camera rays (monocular video) each aim is pulled toward the point of its bone's sphere that lies on the
landmark's viewing ray, which keeps the 3D shape but makes the joints reproject onto the 2D landmarks.
Temporal smoothing (:mod:`warpavatar.prepare.smoothing`) acts on the 3D landmark tracks before the fit, then
on the fitted local rotations and the root position.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from warpavatar.data.types import Skeleton
from warpavatar.geometry import quat_from_matrix, quat_to_matrix
from warpavatar.prepare.smoothing import OneEuroSettings, smooth_positions, smooth_quaternions

__all__ = [
    "LANDMARK_NAMES",
    "JOINT_NAMES",
    "JOINT_PARENTS",
    "BodyMeasurements",
    "RestModel",
    "PoseSmoothing",
    "SkeletonFit",
    "measure_body",
    "build_rest_skeleton",
    "fit_skeleton",
    "forward_kinematics",
    "joint_jitter_mm",
    "mirrored_landmark_order",
]

# MediaPipe Pose's 33 landmarks, in its order.
LANDMARK_NAMES = (
    "nose", "left_eye_inner", "left_eye", "left_eye_outer", "right_eye_inner", "right_eye", "right_eye_outer",
    "left_ear", "right_ear", "mouth_left", "mouth_right", "left_shoulder", "right_shoulder", "left_elbow",
    "right_elbow", "left_wrist", "right_wrist", "left_pinky", "right_pinky", "left_index", "right_index",
    "left_thumb", "right_thumb", "left_hip", "right_hip", "left_knee", "right_knee", "left_ankle", "right_ankle",
    "left_heel", "right_heel", "left_foot_index", "right_foot_index",
)
_L = {name: index for index, name in enumerate(LANDMARK_NAMES)}
LANDMARK_COUNT = len(LANDMARK_NAMES)

JOINT_NAMES = (
    "pelvis", "spine", "chest", "neck", "head",
    "left_shoulder", "left_elbow", "left_wrist",
    "right_shoulder", "right_elbow", "right_wrist",
    "left_hip", "left_knee", "left_ankle",
    "right_hip", "right_knee", "right_ankle",
)
JOINT_PARENTS = (-1, 0, 1, 2, 3, 2, 5, 6, 2, 8, 9, 0, 11, 12, 0, 14, 15)
_J = {name: index for index, name in enumerate(JOINT_NAMES)}
JOINT_COUNT = len(JOINT_NAMES)

# Rest-pose conventions (see the module docstring).
_ARM_ANGLE_RAD = math.radians(45.0)
_FOOT_PITCH_RAD = math.radians(20.0)
_SPINE_FRACTION = 0.3  # the spine's pivot, as a fraction of the way from mid-hip to mid-shoulder
_CHEST_FRACTION = 0.6
_HEAD_TOP_OVER_EAR_WIDTH = 0.75  # the skull's tail lies this many ear widths above the mid-ear point
_X = np.array([1.0, 0.0, 0.0])
_Y = np.array([0.0, 1.0, 0.0])
_Z = np.array([0.0, 0.0, 1.0])
_FORWARD = -_Y  # the rest pose faces -y
# Bend below this sin(angle) uses a pure swing; above the upper one the bend plane fixes the twist.
_BEND_SIN_LOW, _BEND_SIN_HIGH = 0.2, 0.5


@dataclasses.dataclass(frozen=True)
class BodyMeasurements:
    """Constant body dimensions [m], left/right symmetric.

    Attributes:
        torso_length: mid-hip to mid-shoulder.
        neck_length: mid-shoulder to mid-ear.
        hip_width: left hip to right hip.
        shoulder_width: left shoulder to right shoulder.
        upper_arm: shoulder to elbow.
        forearm: elbow to wrist.
        hand: wrist to the midpoint of the index and pinky landmarks.
        hand_width: index to pinky landmark.
        thigh: hip to knee.
        shin: knee to ankle.
        foot: ankle to the toe tip (foot index landmark).
        ear_width: left ear to right ear.
        nose_offset: mid-ear to nose.
        nose_angle_rad: angle between the neck direction and the nose direction, both taken perpendicular to
            the ear line (about 1.7 rad: the nose points forward, a little below the ears).
    """

    torso_length: float
    neck_length: float
    hip_width: float
    shoulder_width: float
    upper_arm: float
    forearm: float
    hand: float
    hand_width: float
    thigh: float
    shin: float
    foot: float
    ear_width: float
    nose_offset: float
    nose_angle_rad: float

    def __post_init__(self):
        for field in dataclasses.fields(self):
            value = getattr(self, field.name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"BodyMeasurements.{field.name} must be finite and positive, got {value}")


@dataclasses.dataclass(frozen=True)
class RestModel:
    """The rest skeleton plus where every modelled landmark sits on it.

    Attributes:
        skeleton: the rest :class:`Skeleton`.
        body: the measurements it was built from.
        landmarks: rest positions of MediaPipe's 33 landmarks [m], shape [33, 3]; NaN for landmarks the model
            does not use (eyes, mouth, thumbs, heels).
        landmark_joints: the joint each landmark moves with, shape [33] int, -1 where unused.
    """

    skeleton: Skeleton
    body: BodyMeasurements
    landmarks: np.ndarray
    landmark_joints: np.ndarray


@dataclasses.dataclass(frozen=True)
class PoseSmoothing:
    """Temporal smoothing of a pose sequence, in two stages (each can be switched off with None).

    The 3D landmark tracks are smoothed before the fit (their viewing rays are not: the fitted joints still
    meet the 2D landmarks), then the fitted local joint rotations and the root position. On the Pose2Sim demo
    (60 fps) the defaults cut the joints' jitter about 3 to 5 times for 0.3 to 1 pixel of extra reprojection
    error (docs/prepare_results.md).

    Attributes:
        landmarks: one-euro parameters of the 3D landmark tracks (``beta`` per m/s).
        rotation: one-euro parameters of the joints' local rotations as quaternions (``beta`` per (rad/2)/s).
        translation: one-euro parameters of the root position (``beta`` per m/s).
        confidence_floor: the smallest gate a sample gets; a landmark at zero visibility still pulls this much.
        confidence_low: visibility at and below which the gate is ``confidence_floor``.
        confidence_high: visibility at and above which a sample is fully trusted.
    """

    landmarks: OneEuroSettings | None = OneEuroSettings(min_cutoff_hz=1.5, beta=2.0)
    rotation: OneEuroSettings | None = OneEuroSettings(min_cutoff_hz=3.0, beta=0.5)
    translation: OneEuroSettings | None = OneEuroSettings(min_cutoff_hz=1.5, beta=2.0)
    confidence_floor: float = 0.05
    confidence_low: float = 0.2
    confidence_high: float = 0.8

    def gate(self, confidence: np.ndarray) -> np.ndarray:
        """Map visibilities in [0, 1] to filter gates in [confidence_floor, 1]."""
        ramp = np.clip((confidence - self.confidence_low) / (self.confidence_high - self.confidence_low), 0.0, 1.0)
        return self.confidence_floor + (1.0 - self.confidence_floor) * ramp


@dataclasses.dataclass(frozen=True)
class SkeletonFit:
    """A fitted pose sequence.

    Attributes:
        rest: the rest model (skeleton, measurements, rest landmarks).
        bone_transforms: rest-to-posed rigid transforms, shape [T, J, 4, 4] float64 (docs/FORMAT.md poses.npz).
        joint_positions: posed joint heads [m], shape [T, J, 3] float64.
        local_rotations: rotation of each joint relative to its parent's (the root's: relative to the world),
            shape [T, J, 3, 3].
        root_positions: posed pelvis pivot [m], shape [T, 3].
        joint_confidence: trust in each joint's fitted rotation, shape [T, J], in [0, 1].
        raw_joint_positions: joint heads of the fit without any temporal smoothing [m], shape [T, J, 3].
    """

    rest: RestModel
    bone_transforms: np.ndarray
    joint_positions: np.ndarray
    local_rotations: np.ndarray
    root_positions: np.ndarray
    joint_confidence: np.ndarray
    raw_joint_positions: np.ndarray

    @property
    def skeleton(self) -> Skeleton:
        """The rest skeleton."""
        return self.rest.skeleton


# ----------------------------------------------------------------------------------------------------------------
# Small batched rotation helpers (arrays of shape [T, 3] and [T, 3, 3]).


def _normalize(vectors: np.ndarray) -> np.ndarray:
    norm = np.linalg.norm(vectors, axis=-1, keepdims=True)
    return vectors / np.maximum(norm, 1e-12)


def _apply(rotations: np.ndarray, vectors: np.ndarray) -> np.ndarray:
    # [T, 3, 3] @ [3] or [T, 3] -> [T, 3]
    if vectors.ndim == 1:
        return np.einsum("tij,j->ti", rotations, vectors)
    return np.einsum("tij,tj->ti", rotations, vectors)


def _basis(primary: np.ndarray, secondary: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Orthonormal frames [T, 3, 3] (columns: primary, secondary made perpendicular, their cross product).

    Returns the frames and the sine of the angle between primary and secondary (0 where degenerate).
    """
    first = _normalize(primary)
    secondary_unit = _normalize(secondary)
    perpendicular = secondary_unit - np.sum(secondary_unit * first, axis=-1, keepdims=True) * first
    sine = np.linalg.norm(perpendicular, axis=-1)
    # A fallback axis where the secondary is parallel to the primary (the weight using it is then zero).
    fallback = np.cross(first, np.where(np.abs(first[..., :1]) < 0.9, _X, _Y))
    perpendicular = np.where((sine > 1e-9)[..., None], perpendicular, fallback)
    second = _normalize(perpendicular)
    third = np.cross(first, second)
    return np.stack([first, second, third], axis=-1), sine


def _frame_rotation(primary, secondary, rest_primary, rest_secondary) -> tuple[np.ndarray, np.ndarray]:
    """Rotations mapping the rest (primary, secondary) frame onto the target one, with the sine as above."""
    count = primary.shape[0]
    target, sine = _basis(primary, secondary)
    rest, _ = _basis(np.broadcast_to(rest_primary, (count, 3)), np.broadcast_to(rest_secondary, (count, 3)))
    return target @ np.swapaxes(rest, -1, -2), sine


def _swing(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Smallest rotations [T, 3, 3] taking unit vectors ``source`` onto ``target`` (both [T, 3])."""
    source = _normalize(source)
    target = _normalize(target)
    axis = np.cross(source, target)
    sine = np.linalg.norm(axis, axis=-1)
    cosine = np.sum(source * target, axis=-1)
    # Opposite vectors: turn half a circle about any axis perpendicular to the source.
    fallback = _normalize(np.cross(source, np.where(np.abs(source[..., :1]) < 0.9, _X, _Y)))
    axis = np.where((sine > 1e-9)[..., None], axis / np.maximum(sine, 1e-12)[..., None], fallback)
    angle = np.arctan2(sine, cosine)
    return _axis_angle_matrix(axis, angle)


def _axis_angle_matrix(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    x, y, z = axis[..., 0], axis[..., 1], axis[..., 2]
    zero = np.zeros_like(x)
    cross = np.stack([
        np.stack([zero, -z, y], axis=-1),
        np.stack([z, zero, -x], axis=-1),
        np.stack([-y, x, zero], axis=-1),
    ], axis=-2)
    sine = np.sin(angle)[..., None, None]
    cosine = np.cos(angle)[..., None, None]
    return np.eye(3) + sine * cross + (1.0 - cosine) * (cross @ cross)


def _slerp_rotations(start: np.ndarray, end: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Interpolate rotations [T, 3, 3] along the shortest arc; weight [T] in [0, 1] (0 gives ``start``)."""
    relative = quat_from_matrix(np.swapaxes(start, -1, -2) @ end)  # w >= 0: shortest arc
    half_angle = np.arccos(np.clip(relative[..., 0], -1.0, 1.0))
    axis = _normalize(relative[..., 1:])
    partial = _axis_angle_matrix(axis, 2.0 * half_angle * weight)
    return start @ partial


# ----------------------------------------------------------------------------------------------------------------
# Measurements and the rest pose.


def _weighted_median(values: np.ndarray, weights: np.ndarray) -> float:
    order = np.argsort(values)
    cumulative = np.cumsum(weights[order])
    return float(values[order][np.searchsorted(cumulative, 0.5 * cumulative[-1])])


def _robust_length(samples: list[tuple[np.ndarray, np.ndarray]], min_confidence: float) -> float:
    # samples: (length [T], confidence [T]) pairs, pooled (left and right together). NaN where undefined.
    lengths = np.concatenate([length for length, _ in samples])
    confidence = np.concatenate([conf for _, conf in samples])
    valid = np.isfinite(lengths) & np.isfinite(confidence) & (lengths > 0)
    trusted = valid & (confidence >= min_confidence)
    chosen = trusted if trusted.any() else valid
    if not chosen.any():
        return float("nan")
    return _weighted_median(lengths[chosen], np.maximum(confidence[chosen], 1e-3))


def _midpoint(points: np.ndarray, first: str, second: str) -> np.ndarray:
    return 0.5 * (points[..., _L[first], :] + points[..., _L[second], :])


def _pair_confidence(confidence: np.ndarray, *names: str) -> np.ndarray:
    return np.min(np.stack([confidence[..., _L[name]] for name in names], axis=-1), axis=-1)


def measure_body(landmarks: np.ndarray, confidence: np.ndarray, *, min_confidence: float = 0.5) -> BodyMeasurements:
    """Robust constant body dimensions from landmark tracks: confidence-weighted medians over frames.

    Left and right samples are pooled, so the result is symmetric. Each length uses the frames where both of
    its end points are at least ``min_confidence`` (all finite frames if there are none).

    Args:
        landmarks: 3D landmarks [m], shape [T, 33, 3] (MediaPipe order); NaN where missing.
        confidence: visibility in [0, 1], shape [T, 33].
        min_confidence: visibility a frame needs to count.

    Returns:
        The :class:`BodyMeasurements`.

    Raises:
        ValueError: a dimension cannot be measured in any frame.
    """
    landmarks, confidence = _check_landmarks(landmarks, confidence)
    points = landmarks

    def segment(first: str, second: str):
        length = np.linalg.norm(points[:, _L[first]] - points[:, _L[second]], axis=-1)
        return length, _pair_confidence(confidence, first, second)

    def sides(first: str, second: str):
        return [segment(f"left_{first}", f"left_{second}"), segment(f"right_{first}", f"right_{second}")]

    mid_hip = _midpoint(points, "left_hip", "right_hip")
    mid_shoulder = _midpoint(points, "left_shoulder", "right_shoulder")
    mid_ear = _midpoint(points, "left_ear", "right_ear")
    torso_confidence = _pair_confidence(confidence, "left_hip", "right_hip", "left_shoulder", "right_shoulder")
    neck_confidence = _pair_confidence(confidence, "left_shoulder", "right_shoulder", "left_ear", "right_ear")
    head_confidence = _pair_confidence(confidence, "left_ear", "right_ear", "nose")
    hand_samples = []
    for side in ("left", "right"):
        hand_centre = _midpoint(points, f"{side}_index", f"{side}_pinky")
        hand_samples.append((
            np.linalg.norm(hand_centre - points[:, _L[f"{side}_wrist"]], axis=-1),
            _pair_confidence(confidence, f"{side}_wrist", f"{side}_index", f"{side}_pinky"),
        ))
    # The nose's angle from the neck direction, both perpendicular to the ear line.
    ear_axis = _normalize(points[:, _L["left_ear"]] - points[:, _L["right_ear"]])

    def perpendicular_to_ears(vectors):
        return _normalize(vectors - np.sum(vectors * ear_axis, axis=-1, keepdims=True) * ear_axis)

    nose_direction = perpendicular_to_ears(points[:, _L["nose"]] - mid_ear)
    neck_direction = perpendicular_to_ears(mid_ear - mid_shoulder)
    nose_angle = np.arccos(np.clip(np.sum(nose_direction * neck_direction, axis=-1), -1.0, 1.0))

    def between(first, second, trust):
        return [(np.linalg.norm(first - second, axis=-1), trust)]

    values = {
        "torso_length": _robust_length(between(mid_shoulder, mid_hip, torso_confidence), min_confidence),
        "neck_length": _robust_length(between(mid_ear, mid_shoulder, neck_confidence), min_confidence),
        "hip_width": _robust_length([segment("left_hip", "right_hip")], min_confidence),
        "shoulder_width": _robust_length([segment("left_shoulder", "right_shoulder")], min_confidence),
        "upper_arm": _robust_length(sides("shoulder", "elbow"), min_confidence),
        "forearm": _robust_length(sides("elbow", "wrist"), min_confidence),
        "hand": _robust_length(hand_samples, min_confidence),
        "hand_width": _robust_length(sides("index", "pinky"), min_confidence),
        "thigh": _robust_length(sides("hip", "knee"), min_confidence),
        "shin": _robust_length(sides("knee", "ankle"), min_confidence),
        "foot": _robust_length(sides("ankle", "foot_index"), min_confidence),
        "ear_width": _robust_length([segment("left_ear", "right_ear")], min_confidence),
        "nose_offset": _robust_length(between(points[:, _L["nose"]], mid_ear, head_confidence), min_confidence),
        "nose_angle_rad": _robust_length([(nose_angle, np.minimum(head_confidence, neck_confidence))], min_confidence),
    }
    missing = [name for name, value in values.items() if not math.isfinite(value)]
    if missing:
        raise ValueError(f"cannot measure {', '.join(missing)}: the landmarks it needs are never finite")
    return BodyMeasurements(**values)


def build_rest_skeleton(body: BodyMeasurements) -> RestModel:
    """The rest skeleton and rest landmark layout for some body measurements (conventions: module docstring).

    Args:
        body: constant body dimensions [m].

    Returns:
        The :class:`RestModel`: joints standing on z = 0 with the pelvis above the origin.
    """
    heads = np.zeros((JOINT_COUNT, 3))
    tails = np.zeros((JOINT_COUNT, 3))
    landmarks = np.full((LANDMARK_COUNT, 3), np.nan)
    landmark_joints = np.full(LANDMARK_COUNT, -1, dtype=np.int64)

    def place(joint: str, head, tail):
        heads[_J[joint]] = head
        tails[_J[joint]] = tail

    def attach(landmark: str, joint: str, position):
        landmarks[_L[landmark]] = position
        landmark_joints[_L[landmark]] = _J[joint]

    def limb(joints: list[str], points: list[np.ndarray], parent: str):
        # Joints in a row: each bone runs from its point to the next; the landmark named like a joint sits at
        # its pivot and moves with the joint before it (the first with ``parent``).
        for joint, head, tail in zip(joints, points, points[1:]):
            place(joint, head, tail)
        for landmark, holder, position in zip(joints, [parent, *joints[:-1]], points):
            attach(landmark, holder, position)

    torso = body.torso_length
    neck_base = torso * _Z
    mid_ear = neck_base + body.neck_length * _Z
    place("pelvis", np.zeros(3), _SPINE_FRACTION * torso * _Z)
    place("spine", _SPINE_FRACTION * torso * _Z, _CHEST_FRACTION * torso * _Z)
    place("chest", _CHEST_FRACTION * torso * _Z, neck_base)
    place("neck", neck_base, mid_ear)
    place("head", mid_ear, mid_ear + _HEAD_TOP_OVER_EAR_WIDTH * body.ear_width * _Z)
    nose_direction = math.sin(body.nose_angle_rad) * _FORWARD + math.cos(body.nose_angle_rad) * _Z
    attach("nose", "head", mid_ear + body.nose_offset * nose_direction)
    for side, sign in (("left", 1.0), ("right", -1.0)):
        attach(f"{side}_ear", "head", mid_ear + 0.5 * sign * body.ear_width * _X)
        arm = np.array([sign * math.sin(_ARM_ANGLE_RAD), 0.0, -math.cos(_ARM_ANGLE_RAD)])
        shoulder = neck_base + 0.5 * sign * body.shoulder_width * _X
        elbow = shoulder + body.upper_arm * arm
        wrist = elbow + body.forearm * arm
        hand_centre = wrist + body.hand * arm
        limb([f"{side}_shoulder", f"{side}_elbow", f"{side}_wrist"], [shoulder, elbow, wrist, hand_centre], "chest")
        # Palms face the thighs: the index finger's side is forward.
        attach(f"{side}_index", f"{side}_wrist", hand_centre + 0.5 * body.hand_width * _FORWARD)
        attach(f"{side}_pinky", f"{side}_wrist", hand_centre - 0.5 * body.hand_width * _FORWARD)
        hip = 0.5 * sign * body.hip_width * _X
        knee = hip - body.thigh * _Z
        ankle = knee - body.shin * _Z
        toe = ankle + body.foot * (math.cos(_FOOT_PITCH_RAD) * _FORWARD - math.sin(_FOOT_PITCH_RAD) * _Z)
        limb([f"{side}_hip", f"{side}_knee", f"{side}_ankle"], [hip, knee, ankle, toe], "pelvis")
        attach(f"{side}_foot_index", f"{side}_ankle", toe)
    lift = -min(heads[:, 2].min(), tails[:, 2].min())
    heads[:, 2] += lift
    tails[:, 2] += lift
    landmarks[:, 2] += lift
    skeleton = Skeleton(names=JOINT_NAMES, parents=np.asarray(JOINT_PARENTS), heads=heads, tails=tails,
                        dtype=np.float64)
    return RestModel(skeleton=skeleton, body=body, landmarks=landmarks, landmark_joints=landmark_joints)


# ----------------------------------------------------------------------------------------------------------------
# Fitting.


def _check_landmarks(landmarks, confidence) -> tuple[np.ndarray, np.ndarray]:
    landmarks = np.asarray(landmarks, dtype=np.float64)
    confidence = np.asarray(confidence, dtype=np.float64)
    if landmarks.ndim != 3 or landmarks.shape[1:] != (LANDMARK_COUNT, 3):
        raise ValueError(f"landmarks must have shape [T, {LANDMARK_COUNT}, 3], got {landmarks.shape}")
    if confidence.shape != landmarks.shape[:2]:
        raise ValueError(f"confidence must have shape {landmarks.shape[:2]}, got {confidence.shape}")
    if landmarks.shape[0] == 0:
        raise ValueError("landmarks hold no frame (T = 0)")
    if np.isinf(landmarks).any():
        raise ValueError("landmarks must be finite or NaN (missing), not infinite")
    confidence = np.where(np.isfinite(confidence), np.clip(confidence, 0.0, 1.0), 0.0)
    confidence = np.where(np.isfinite(landmarks).all(axis=-1), confidence, 0.0)
    return landmarks, confidence


def _fill_gaps(landmarks: np.ndarray) -> np.ndarray:
    """Linear interpolation over time of missing landmarks (constant beyond the first and last valid frame)."""
    filled = landmarks.copy()
    frames = np.arange(landmarks.shape[0])
    for landmark in range(landmarks.shape[1]):
        valid = np.isfinite(landmarks[:, landmark]).all(axis=-1)
        if valid.all():
            continue
        if not valid.any():
            raise ValueError(f"landmark {LANDMARK_NAMES[landmark]!r} is missing in every frame")
        for axis in range(3):
            filled[:, landmark, axis] = np.interp(frames, frames[valid], landmarks[valid, landmark, axis])
    return filled


class _RayTargets:
    """Viewing rays of the landmarks (monocular fits): origin [T, 3], unit directions [T, 33, 3], weights [T, 33]."""

    def __init__(self, origins, directions, weights):
        self.origins = origins
        self.directions = directions
        self.weights = weights

    def ray(self, names: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
        indices = [_L[name] for name in names]
        direction = _normalize(self.directions[:, indices].sum(axis=1))
        weight = self.weights[:, indices].min(axis=1)
        return direction, weight


def _aim(
    pivot: np.ndarray, target: np.ndarray, length: float, rays: _RayTargets | None, names: tuple[str, ...]
) -> np.ndarray:
    """Unit direction [T, 3] from ``pivot`` toward the measured ``target``, pulled onto the target's viewing ray.

    With rays, the point at distance ``length`` from the pivot that lies on the ray (the intersection nearest
    the measured target, or the ray's closest approach when the sphere misses it) gives a second direction;
    the two are blended by the ray's weight.
    """
    measured = _normalize(target - pivot)
    if rays is None:
        return measured
    direction, weight = rays.ray(names)
    offset = pivot - rays.origins
    along = np.sum(direction * offset, axis=-1)
    discriminant = along * along - (np.sum(offset * offset, axis=-1) - length * length)
    root = np.sqrt(np.maximum(discriminant, 0.0))
    near = rays.origins + (along - root)[:, None] * direction
    far = rays.origins + (along + root)[:, None] * direction
    pick_far = np.linalg.norm(far - target, axis=-1) < np.linalg.norm(near - target, axis=-1)
    on_ray = np.where(pick_far[:, None], far, near)
    closest = rays.origins + np.maximum(along, 0.0)[:, None] * direction
    on_ray = np.where((discriminant >= 0.0)[:, None], on_ray, closest)
    snapped = _normalize(on_ray - pivot)
    blended = (1.0 - weight)[:, None] * measured + weight[:, None] * snapped
    return np.where((np.linalg.norm(blended, axis=-1) > 1e-6)[:, None], _normalize(blended), snapped)


def _bend_weight(sine: np.ndarray) -> np.ndarray:
    return np.clip((sine - _BEND_SIN_LOW) / (_BEND_SIN_HIGH - _BEND_SIN_LOW), 0.0, 1.0)


def _fit_frames(points: np.ndarray, confidence: np.ndarray, rest: RestModel, rays: _RayTargets | None):
    """Per-frame world rotations [T, J, 3, 3], root positions [T, 3] and joint confidences [T, J], no smoothing."""
    frame_count = points.shape[0]
    heads = rest.skeleton.heads
    rotations = np.zeros((frame_count, JOINT_COUNT, 3, 3))
    positions = np.zeros((frame_count, JOINT_COUNT, 3))
    joint_confidence = np.zeros((frame_count, JOINT_COUNT))

    def point(name: str) -> np.ndarray:
        return points[:, _L[name]]

    def conf(*names: str) -> np.ndarray:
        return _pair_confidence(confidence, *names)

    def place_child(joint: str):
        # Forward kinematics of one joint's pivot from its parent's.
        index = _J[joint]
        parent = JOINT_PARENTS[index]
        positions[:, index] = positions[:, parent] + _apply(rotations[:, parent], heads[index] - heads[parent])

    def bone_length(joint: str) -> float:
        index = _J[joint]
        return float(np.linalg.norm(rest.skeleton.tails[index] - heads[index]))

    def rest_direction(joint: str) -> np.ndarray:
        index = _J[joint]
        return _normalize(rest.skeleton.tails[index] - heads[index])

    def swing_from_parent(joint: str, aim: np.ndarray) -> np.ndarray:
        parent_rotation = rotations[:, JOINT_PARENTS[_J[joint]]]
        return _swing(_apply(parent_rotation, rest_direction(joint)), aim) @ parent_rotation

    mid_hip = _midpoint(points, "left_hip", "right_hip")
    mid_shoulder = _midpoint(points, "left_shoulder", "right_shoulder")
    mid_ear = _midpoint(points, "left_ear", "right_ear")
    hip_line = point("left_hip") - point("right_hip")
    shoulder_line = point("left_shoulder") - point("right_shoulder")

    # Torso.
    positions[:, _J["pelvis"]] = mid_hip
    rotations[:, _J["pelvis"]], _ = _frame_rotation(hip_line, mid_shoulder - mid_hip, _X, _Z)
    joint_confidence[:, _J["pelvis"]] = conf("left_hip", "right_hip", "left_shoulder", "right_shoulder")
    place_child("spine")
    torso_aim = _aim(
        positions[:, _J["spine"]], mid_shoulder,
        float(np.linalg.norm(heads[_J["neck"]] - heads[_J["spine"]])), rays, ("left_shoulder", "right_shoulder"),
    )
    rotations[:, _J["chest"]], _ = _frame_rotation(torso_aim, shoulder_line, _Z, _X)
    rotations[:, _J["spine"]], _ = _frame_rotation(torso_aim, _normalize(hip_line) + _normalize(shoulder_line), _Z, _X)
    joint_confidence[:, _J["spine"]] = joint_confidence[:, _J["pelvis"]]
    joint_confidence[:, _J["chest"]] = conf("left_shoulder", "right_shoulder")
    place_child("chest")
    place_child("neck")

    # Neck and head: the head's frame first, then the neck aims at the head's pivot (the mid-ear point).
    rest_nose = rest.landmarks[_L["nose"]] - heads[_J["head"]]
    ear_line = point("left_ear") - point("right_ear")
    rotations[:, _J["head"]], _ = _frame_rotation(ear_line, point("nose") - mid_ear, _X, rest_nose)
    neck_aim = _aim(positions[:, _J["neck"]], mid_ear, bone_length("neck"), rays, ("left_ear", "right_ear"))
    rotations[:, _J["neck"]] = swing_from_parent("neck", neck_aim)
    joint_confidence[:, _J["neck"]] = conf("left_ear", "right_ear")
    joint_confidence[:, _J["head"]] = conf("left_ear", "right_ear", "nose")
    place_child("head")

    # Limbs: (root joint of the chain, [(joint, aim landmark(s)), ...], the bend's rest direction).
    for side in ("left", "right"):
        limbs = (
            (f"{side}_shoulder", (f"{side}_elbow",), (f"{side}_wrist",), (f"{side}_index", f"{side}_pinky"), _FORWARD),
            (f"{side}_hip", (f"{side}_knee",), (f"{side}_ankle",), (f"{side}_foot_index",), _Y),
        )
        for upper, middle_names, lower_names, end_names, bend_rest in limbs:
            middle_joint = JOINT_NAMES[_J[upper] + 1]
            lower_joint = JOINT_NAMES[_J[upper] + 2]
            place_child(upper)
            middle_target = np.mean([point(name) for name in middle_names], axis=0)
            lower_target = np.mean([point(name) for name in lower_names], axis=0)
            end_target = np.mean([point(name) for name in end_names], axis=0)
            # Upper bone: aim plus the bend-plane twist, faded toward a pure swing when nearly straight.
            aim = _aim(positions[:, _J[upper]], middle_target, bone_length(upper), rays, middle_names)
            swing = swing_from_parent(upper, aim)
            framed, sine = _frame_rotation(aim, lower_target - middle_target, rest_direction(upper), bend_rest)
            bend = _bend_weight(sine)
            rotations[:, _J[upper]] = _slerp_rotations(swing, framed, bend)
            joint_confidence[:, _J[upper]] = conf(*middle_names) * (1.0 - bend * (1.0 - conf(*lower_names)))
            # Middle and lower bones: swings.
            place_child(middle_joint)
            aim = _aim(positions[:, _J[middle_joint]], lower_target, bone_length(middle_joint), rays, lower_names)
            rotations[:, _J[middle_joint]] = swing_from_parent(middle_joint, aim)
            joint_confidence[:, _J[middle_joint]] = conf(*lower_names)
            place_child(lower_joint)
            aim = _aim(positions[:, _J[lower_joint]], end_target, bone_length(lower_joint), rays, end_names)
            rotations[:, _J[lower_joint]] = swing_from_parent(lower_joint, aim)
            joint_confidence[:, _J[lower_joint]] = conf(*end_names)
    return rotations, positions[:, 0].copy(), joint_confidence


def forward_kinematics(
    skeleton: Skeleton, local_rotations: np.ndarray, root_positions: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Compose local rotations along the chain into bone transforms.

    Args:
        skeleton: the rest skeleton (J joints, parents before children).
        local_rotations: rotation of each joint relative to its parent's, the root's relative to the world;
            shape [T, J, 3, 3].
        root_positions: posed root pivot [m], shape [T, 3].

    Returns:
        ``(bone_transforms, joint_positions)``: rest-to-posed rigid transforms [T, J, 4, 4] and posed joint
        heads [T, J, 3], float64.
    """
    local_rotations = np.asarray(local_rotations, dtype=np.float64)
    root_positions = np.asarray(root_positions, dtype=np.float64)
    joint_count = skeleton.joint_count
    if local_rotations.ndim != 4 or local_rotations.shape[1:] != (joint_count, 3, 3):
        raise ValueError(f"local_rotations must have shape [T, {joint_count}, 3, 3], got {local_rotations.shape}")
    frame_count = local_rotations.shape[0]
    if root_positions.shape != (frame_count, 3):
        raise ValueError(f"root_positions must have shape [{frame_count}, 3], got {root_positions.shape}")
    world = np.zeros_like(local_rotations)
    positions = np.zeros((frame_count, joint_count, 3))
    for joint, parent in enumerate(skeleton.parents):
        if parent < 0:
            world[:, joint] = local_rotations[:, joint]
            positions[:, joint] = root_positions
        else:
            world[:, joint] = world[:, parent] @ local_rotations[:, joint]
            offset = skeleton.heads[joint] - skeleton.heads[parent]
            positions[:, joint] = positions[:, parent] + _apply(world[:, parent], offset)
    transforms = np.zeros((frame_count, joint_count, 4, 4))
    transforms[..., :3, :3] = world
    transforms[..., :3, 3] = positions - np.einsum("tjab,jb->tja", world, skeleton.heads)
    transforms[..., 3, 3] = 1.0
    return transforms, positions


def _local_from_world(world: np.ndarray) -> np.ndarray:
    local = world.copy()
    for joint, parent in enumerate(JOINT_PARENTS):
        if parent >= 0:
            local[:, joint] = np.swapaxes(world[:, parent], -1, -2) @ world[:, joint]
    return local


def fit_skeleton(
    landmarks: np.ndarray,
    confidence: np.ndarray,
    *,
    fps: float = 30.0,
    smoothing: PoseSmoothing | None = PoseSmoothing(),
    body: BodyMeasurements | None = None,
    ray_origins: np.ndarray | None = None,
    ray_directions: np.ndarray | None = None,
    ray_weights: np.ndarray | None = None,
) -> SkeletonFit:
    """Fit the 17-joint skeleton to 3D landmark tracks.

    Args:
        landmarks: MediaPipe's 33 landmarks in world coordinates [m], shape [T, 33, 3] float; NaN where missing
            (filled by interpolation over time, with zero confidence).
        confidence: visibility of each landmark in [0, 1], shape [T, 33].
        fps: frame rate [Hz] for the smoothing filters.
        smoothing: temporal smoothing, or None for the raw per-frame fit.
        body: body dimensions; measured from the landmarks by :func:`measure_body` when None.
        ray_origins: camera centre [m] in world coordinates, shape [3] or [T, 3]; with ``ray_directions`` it
            pulls every aimed bone onto its landmark's viewing ray (monocular video).
        ray_directions: unit viewing-ray directions of the 2D landmarks, world frame, shape [T, 33, 3].
        ray_weights: how strongly each ray pulls, in [0, 1], shape [T, 33]; default ``confidence``.

    Returns:
        A :class:`SkeletonFit`.

    Raises:
        ValueError: bad shapes, non-finite values where they are not allowed, or landmarks never present.
    """
    landmarks, confidence = _check_landmarks(landmarks, confidence)
    if not (math.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be positive, got {fps}")
    frame_count = landmarks.shape[0]
    rays = None
    if (ray_origins is None) != (ray_directions is None):
        raise ValueError("ray_origins and ray_directions must be given together")
    if ray_directions is not None:
        ray_directions = np.asarray(ray_directions, dtype=np.float64)
        ray_origins = np.broadcast_to(np.asarray(ray_origins, dtype=np.float64), (frame_count, 3)).copy()
        if ray_directions.shape != landmarks.shape:
            raise ValueError(f"ray_directions must have shape {landmarks.shape}, got {ray_directions.shape}")
        weights = confidence if ray_weights is None else np.asarray(ray_weights, dtype=np.float64)
        if weights.shape != confidence.shape:
            raise ValueError(f"ray_weights must have shape {confidence.shape}, got {weights.shape}")
        usable = np.isfinite(ray_directions).all(axis=-1) & np.isfinite(weights)
        if not np.isfinite(ray_origins).all():
            raise ValueError("ray_origins must be finite")
        rays = _RayTargets(
            ray_origins, np.where(usable[..., None], _normalize(np.nan_to_num(ray_directions)), _Z),
            np.where(usable, np.clip(weights, 0.0, 1.0), 0.0),
        )
    if body is None:
        body = measure_body(landmarks, confidence)
    rest = build_rest_skeleton(body)
    filled = _fill_gaps(landmarks)
    smooth = smoothing is not None and frame_count > 1
    raw_rotations, raw_roots, joint_confidence = _fit_frames(filled, confidence, rest, rays)
    _, raw_positions = forward_kinematics(rest.skeleton, _local_from_world(raw_rotations), raw_roots)
    if smooth and smoothing.landmarks is not None:
        filled = smooth_positions(
            filled, rate_hz=fps, settings=smoothing.landmarks, confidence=smoothing.gate(confidence),
        )
        world_rotations, root_positions, joint_confidence = _fit_frames(filled, confidence, rest, rays)
    else:
        world_rotations, root_positions = raw_rotations, raw_roots
    local_rotations = _local_from_world(world_rotations)
    if smooth and smoothing.rotation is not None:
        quaternions = smooth_quaternions(
            quat_from_matrix(local_rotations), rate_hz=fps, settings=smoothing.rotation,
            confidence=smoothing.gate(joint_confidence),
        )
        local_rotations = quat_to_matrix(_normalize(quaternions))
    if smooth and smoothing.translation is not None:
        root_positions = smooth_positions(
            root_positions, rate_hz=fps, settings=smoothing.translation,
            confidence=smoothing.gate(joint_confidence[:, 0]),
        )
    transforms, positions = forward_kinematics(rest.skeleton, local_rotations, root_positions)
    return SkeletonFit(
        rest=rest, bone_transforms=transforms, joint_positions=positions, local_rotations=local_rotations,
        root_positions=root_positions, joint_confidence=joint_confidence, raw_joint_positions=raw_positions,
    )


def joint_jitter_mm(joint_positions: np.ndarray) -> dict:
    """Jitter of joint tracks: the size of the second difference ``|p[t+1] - 2 p[t] + p[t-1]|`` [mm / frame^2].

    Args:
        joint_positions: shape [T, J, 3], metres.

    Returns:
        ``{"median": ..., "p90": ..., "mean": ...}`` over all joints and frames (zeros when T < 3).
    """
    joint_positions = np.asarray(joint_positions, dtype=np.float64)
    if joint_positions.ndim != 3 or joint_positions.shape[-1] != 3:
        raise ValueError(f"joint_positions must have shape [T, J, 3], got {joint_positions.shape}")
    if joint_positions.shape[0] < 3:
        return {"median": 0.0, "p90": 0.0, "mean": 0.0}
    second = joint_positions[2:] - 2.0 * joint_positions[1:-1] + joint_positions[:-2]
    size = np.linalg.norm(second, axis=-1).reshape(-1) * 1000.0
    size = size[np.isfinite(size)]
    return {"median": float(np.median(size)), "p90": float(np.percentile(size, 90)), "mean": float(size.mean())}


def mirrored_landmark_order(*, part: str = "all") -> np.ndarray:
    """The permutation of the 33 landmarks that exchanges left and right labels.

    Args:
        part: ``"all"`` (every left/right pair), ``"face"`` (eyes, ears, mouth corners), ``"arms"`` (shoulders
            to fingers) or ``"legs"`` (hips to toes).

    Returns:
        Index array of shape [33]: ``landmarks[..., order, :]`` is the relabeled set.
    """
    arms = {"shoulder", "elbow", "wrist", "pinky", "index", "thumb"}
    legs = {"hip", "knee", "ankle", "heel", "foot_index"}
    face = {"eye_inner", "eye", "eye_outer", "ear", "mouth_"}
    if part not in ("all", "face", "arms", "legs"):
        raise ValueError(f"part must be 'all', 'face', 'arms' or 'legs', got {part!r}")
    order = np.arange(LANDMARK_COUNT)
    for index, name in enumerate(LANDMARK_NAMES):
        if "left" not in name:
            continue
        body_part = name.replace("left_", "").replace("left", "")
        chosen = {"all": body_part, "face": face, "arms": arms, "legs": legs}[part]
        if part != "all" and body_part not in chosen:
            continue
        partner = _L[name.replace("left", "right")]
        order[index], order[partner] = partner, index
    return order
