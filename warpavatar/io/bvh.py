"""Biovision ``.bvh`` motion capture: parsing, forward kinematics and retargeting to warpavatar's skeleton.

BVH conventions used here (those of Blender's and MotionBuilder's importers):
    * a joint's local transform is ``T(offset, with any position channels replacing its components) @ R``,
      where ``R`` is the product of its rotation channels in the order they are listed, e.g.
      ``CHANNELS 3 Zrotation Xrotation Yrotation`` gives ``R = Rz(z) @ Rx(x) @ Ry(y)`` (column vectors,
      angles in degrees, right-handed);
    * the rest pose is the hierarchy with every channel at zero rotation and every joint at its OFFSET;
    * the file's floor is the plane ``up = 0`` (Y up unless told otherwise).

Retargeting (:func:`retarget_bvh`) drives each of our joints by the world rotation of the BVH joint it is
mapped to, relative to the BVH rest pose, and keeps *our* bone lengths: see its docstring. It assumes both
rest poses have their limbs in similar directions (both T-pose, or both A-pose).
"""

from __future__ import annotations

import dataclasses
import os
import re

import numpy as np

from warpavatar.data.checks import FPS_RANGE
from warpavatar.data.types import MAX_JOINT_DEPTH

__all__ = ["BvhError", "BvhMotion", "parse_bvh", "bvh_rest_positions", "bvh_forward_kinematics",
           "match_joint_names", "retarget_bvh", "up_axis_rotation"]

_AXES = {"X": 0, "Y": 1, "Z": 2}
_CHANNELS = {f"{axis}{kind}" for axis in "XYZ" for kind in ("position", "rotation")}


class BvhError(ValueError):
    """A BVH file that cannot be parsed, or a motion that cannot be retargeted."""


@dataclasses.dataclass
class BvhMotion:
    """The contents of a BVH file.

    Attributes:
        names: J joint names, in file order (parents before children); End Sites are not joints.
        parents: [J] int32 parent index, -1 for a root.
        offsets: [J,3] float64 rest offset of each joint from its parent (file units; a root's is its rest
            world position).
        channels: J tuples of channel names ("Xposition", "Zrotation", ...), in file order.
        end_site_offsets: [E,3] float64 offsets of the End Sites from their joints (file units).
        end_site_parents: [E] int32 joint each End Site hangs from.
        motion: [T,C] float64 channel values per frame (C = total channel count; rotations in degrees).
        frame_time: seconds per frame.
        path: the file it came from (for messages).
    """

    names: list[str]
    parents: np.ndarray
    offsets: np.ndarray
    channels: list[tuple[str, ...]]
    end_site_offsets: np.ndarray
    end_site_parents: np.ndarray
    motion: np.ndarray
    frame_time: float
    path: str = ""

    @property
    def joint_count(self) -> int:
        return len(self.names)

    @property
    def frame_count(self) -> int:
        return int(self.motion.shape[0])

    @property
    def fps(self) -> float:
        return 1.0 / self.frame_time


def parse_bvh(path: str | os.PathLike) -> BvhMotion:
    """Parse a BVH file (HIERARCHY with ROOT/JOINT/End Site, OFFSET, CHANNELS; MOTION with Frames and
    Frame Time). Several ROOTs are accepted.

    Args:
        path: the ``.bvh`` file.

    Returns:
        the :class:`BvhMotion`.

    Raises:
        BvhError: malformed file (the message names the file and line).
        OSError: the file cannot be read.
    """
    path = os.fspath(path)
    with open(path, encoding="utf-8", errors="replace") as stream:
        lines = stream.read().splitlines()
    # Tokens of the hierarchy with their line numbers; the MOTION block is read line by line afterwards.
    tokens: list[tuple[str, int]] = []
    motion_line = None
    for number, line in enumerate(lines, start=1):
        words = line.replace("{", " { ").replace("}", " } ").split()
        if words and words[0].upper() == "MOTION":
            motion_line = number
            break
        tokens.extend((word, number) for word in words)
    if not tokens or tokens[0][0].upper() != "HIERARCHY":
        raise BvhError(f"{path}: not a BVH file (no HIERARCHY at the start)")
    if motion_line is None:
        raise BvhError(f"{path}: no MOTION section")

    names: list[str] = []
    parents: list[int] = []
    offsets: list[list[float]] = []
    channels: list[tuple[str, ...]] = []
    end_offsets: list[list[float]] = []
    end_parents: list[int] = []
    position = 1

    def fail(message: str) -> BvhError:
        line = tokens[min(position, len(tokens) - 1)][1]
        return BvhError(f"{path}, line {line}: {message}")

    def expect(word: str) -> None:
        nonlocal position
        if position >= len(tokens) or tokens[position][0] != word:
            found = tokens[position][0] if position < len(tokens) else "end of hierarchy"
            raise fail(f"expected {word!r}, found {found!r}")
        position += 1

    def read_floats(count: int) -> list[float]:
        nonlocal position
        try:
            values = [float(tokens[position + i][0]) for i in range(count)]
        except (ValueError, IndexError):
            raise fail(f"expected {count} numbers") from None
        position += count
        return values

    def read_joint(parent: int, depth: int = 1) -> None:
        """Parse ``NAME { OFFSET ... CHANNELS ... children }``; ``position`` is just after ROOT/JOINT."""
        nonlocal position
        if depth > MAX_JOINT_DEPTH:
            raise fail(f"joints nested more than {MAX_JOINT_DEPTH} deep, more than expected of a skeleton (a "
                       "missing '}'?)")
        line = tokens[position][1] if position < len(tokens) else -1
        name_words = []
        while position < len(tokens) and tokens[position][1] == line and tokens[position][0] != "{":
            name_words.append(tokens[position][0])
            position += 1
        if not name_words:
            raise fail("joint without a name")
        index = len(names)
        names.append(" ".join(name_words))
        parents.append(parent)
        expect("{")
        expect("OFFSET")
        offsets.append(read_floats(3))
        joint_channels: tuple[str, ...] = ()
        if position < len(tokens) and tokens[position][0] == "CHANNELS":
            position += 1
            try:
                channel_count = int(tokens[position][0])
            except (ValueError, IndexError):
                raise fail("CHANNELS needs a count") from None
            position += 1
            joint_channels = tuple(word for word, _ in tokens[position:position + channel_count])
            unknown = [word for word in joint_channels if word not in _CHANNELS]
            if len(joint_channels) != channel_count or unknown:
                raise fail(f"bad channels {list(joint_channels)} (allowed: X/Y/Z + position/rotation)")
            position += channel_count
        channels.append(joint_channels)
        while position < len(tokens) and tokens[position][0] != "}":
            keyword = tokens[position][0]
            if keyword == "JOINT":
                position += 1
                read_joint(index, depth + 1)
            elif keyword == "End" and position + 1 < len(tokens) and tokens[position + 1][0] == "Site":
                position += 2
                expect("{")
                expect("OFFSET")
                end_offsets.append(read_floats(3))
                end_parents.append(index)
                expect("}")
            else:
                raise fail(f"unexpected {keyword!r} in joint {names[index]!r}")
        expect("}")

    while position < len(tokens):
        if tokens[position][0] != "ROOT":
            raise fail(f"expected ROOT, found {tokens[position][0]!r}")
        position += 1
        read_joint(-1)
    if not names:
        raise BvhError(f"{path}: the hierarchy has no joints")

    # MOTION: "Frames: N", "Frame Time: dt", then N rows of values.
    header = []
    row = motion_line
    while len(header) < 2 and row < len(lines):
        text = lines[row].strip()
        row += 1
        if text:
            header.append((text, row))
    frames_match = re.fullmatch(r"Frames:\s*(\d+)", header[0][0]) if header else None
    time_match = re.fullmatch(r"Frame\s+Time:\s*(\S+)", header[1][0]) if len(header) > 1 else None
    if not frames_match or not time_match:
        raise BvhError(f"{path}, line {motion_line}: MOTION must be followed by 'Frames: N' and 'Frame Time: dt'")
    frame_count = int(frames_match.group(1))
    try:
        frame_time = float(time_match.group(1))
    except ValueError:
        raise BvhError(f"{path}, line {header[1][1]}: bad Frame Time {time_match.group(1)!r}") from None
    shortest, longest = 1.0 / FPS_RANGE[1], 1.0 / FPS_RANGE[0]
    if not (np.isfinite(frame_time) and shortest <= frame_time <= longest):
        raise BvhError(f"{path}, line {header[1][1]}: Frame Time must be from {shortest:g} to {longest:g} seconds "
                       f"({FPS_RANGE[1]:g} to {FPS_RANGE[0]:g} frames per second), got {time_match.group(1)}")
    channel_total = sum(len(c) for c in channels)
    text = " ".join(lines[row:]).split()
    if len(text) != frame_count * channel_total:
        raise BvhError(f"{path}: MOTION has {len(text)} values, expected Frames x channels = "
                       f"{frame_count} x {channel_total} = {frame_count * channel_total}")
    try:
        motion = np.array(text, dtype=np.float64).reshape(frame_count, channel_total)
    except ValueError:
        raise BvhError(f"{path}: MOTION holds a value that is not a number") from None
    if not np.isfinite(motion).all():
        raise BvhError(f"{path}: MOTION holds non-finite values")
    return BvhMotion(
        names=names,
        parents=np.asarray(parents, dtype=np.int32),
        offsets=np.asarray(offsets, dtype=np.float64).reshape(-1, 3),
        channels=channels,
        end_site_offsets=np.asarray(end_offsets, dtype=np.float64).reshape(-1, 3),
        end_site_parents=np.asarray(end_parents, dtype=np.int32),
        motion=motion,
        frame_time=frame_time,
        path=path,
    )


def _axis_rotations(axis: int, degrees: np.ndarray) -> np.ndarray:
    """[T] angles in degrees -> [T,3,3] right-handed rotations about axis 0/1/2."""
    radians = np.deg2rad(degrees)
    cos, sin = np.cos(radians), np.sin(radians)
    out = np.zeros(radians.shape + (3, 3))
    i, j = (axis + 1) % 3, (axis + 2) % 3
    out[..., axis, axis] = 1.0
    out[..., i, i] = cos
    out[..., j, j] = cos
    out[..., i, j] = -sin
    out[..., j, i] = sin
    return out


def bvh_rest_positions(bvh: BvhMotion) -> tuple[np.ndarray, np.ndarray]:
    """World positions of the rest pose: joints [J,3] and End Sites [E,3] (float64, file units)."""
    joints = np.zeros((bvh.joint_count, 3))
    for joint, parent in enumerate(bvh.parents):
        joints[joint] = bvh.offsets[joint] + (joints[parent] if parent >= 0 else 0.0)
    ends = joints[bvh.end_site_parents] + bvh.end_site_offsets if len(bvh.end_site_parents) else np.zeros((0, 3))
    return joints, ends


def bvh_forward_kinematics(bvh: BvhMotion) -> tuple[np.ndarray, np.ndarray]:
    """World rotations and positions of every joint in every frame.

    Returns:
        (rotations [T,J,3,3], positions [T,J,3]), float64, file units. In the rest pose (all channels
        zero, no position channels) every rotation is the identity.
    """
    frame_count = bvh.frame_count
    rotations = np.zeros((frame_count, bvh.joint_count, 3, 3))
    positions = np.zeros((frame_count, bvh.joint_count, 3))
    column = 0
    for joint, parent in enumerate(bvh.parents):
        local_rotation = np.broadcast_to(np.eye(3), (frame_count, 3, 3))
        local_translation = np.broadcast_to(bvh.offsets[joint], (frame_count, 3)).copy()
        for channel in bvh.channels[joint]:
            values = bvh.motion[:, column]
            column += 1
            axis = _AXES[channel[0]]
            if channel.endswith("rotation"):
                local_rotation = local_rotation @ _axis_rotations(axis, values)
            else:
                local_translation[:, axis] = values
        if parent < 0:
            rotations[:, joint] = local_rotation
            positions[:, joint] = local_translation
        else:
            rotations[:, joint] = rotations[:, parent] @ local_rotation
            positions[:, joint] = positions[:, parent] + np.einsum("tij,tj->ti", rotations[:, parent],
                                                                   local_translation)
    return rotations, positions


def _axis_vector(up) -> np.ndarray:
    """'Y', '-Z', ... or a 3-vector -> unit float64 vector."""
    if isinstance(up, str):
        match = re.fullmatch(r"([+-]?)([XYZxyz])", up.strip())
        if not match:
            raise BvhError(f"up axis must be 'X', 'Y', 'Z' (optionally signed) or a 3-vector, got {up!r}")
        vector = np.zeros(3)
        vector[_AXES[match.group(2).upper()]] = -1.0 if match.group(1) == "-" else 1.0
        return vector
    vector = np.asarray(up, dtype=np.float64)
    norm = np.linalg.norm(vector) if vector.shape == (3,) else 0.0
    if not np.isfinite(norm) or norm == 0:
        raise BvhError(f"up vector must be a finite non-zero 3-vector, got {up!r}")
    return vector / norm


def up_axis_rotation(source_up, target_up) -> np.ndarray:
    """The smallest rotation [3,3] taking the ``source_up`` direction to ``target_up``.

    Both are axis names ('Y', '-Z', ...) or 3-vectors. From 'Y' to 'Z' it is +90 degrees about X:
    (x, y, z) -> (x, -z, y), so a BVH character facing +Z ends up facing -Y (Blender's convention).
    """
    a, b = _axis_vector(source_up), _axis_vector(target_up)
    axis = np.cross(a, b)
    sin, cos = np.linalg.norm(axis), float(np.dot(a, b))
    if sin < 1e-12:
        if cos > 0:
            return np.eye(3)
        # Opposite directions: half a turn about any axis orthogonal to a.
        helper = np.eye(3)[np.argmin(np.abs(a))]
        axis = np.cross(a, helper)
        axis /= np.linalg.norm(axis)
        return 2.0 * np.outer(axis, axis) - np.eye(3)
    axis /= sin
    cross = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + sin * cross + (1 - cos) * cross @ cross


def _alias_key(name: str) -> str:
    """A loose key for joint names: namespace dropped, case and separators ignored, Left/Right/L/R
    anywhere moved to the front as 'l'/'r' ("mixamorig:LeftArm", "arm_l", "Arm.L" -> "larm")."""
    name = name.split(":")[-1]
    words = [w.lower() for w in re.findall(r"[A-Z]+(?![a-z])|[A-Z]?[a-z]+|\d+", name)]
    synonyms = {"left": "l", "right": "r", "pelvis": "hips"}
    words = [synonyms.get(w, w) for w in words]
    side = [w for w in words if w in ("l", "r")]
    rest = [w for w in words if w not in ("l", "r")]
    return "".join(side[:1] + rest + side[1:])


def match_joint_names(our_names: list[str], bvh_names: list[str], name_map: dict | None = None
                      ) -> dict[int, int]:
    """Which BVH joint drives each of our joints: {our index: bvh index}.

    Args:
        our_names: our joint names.
        bvh_names: the BVH joint names.
        name_map: {our name: BVH name}; only these pairs are used when given. Default: equal names
            ignoring case, then, for joints still unmatched, equal :func:`_alias_key` keys when the key is
            unique on both sides.

    Raises:
        BvhError: a name in ``name_map`` that is not in the skeleton or the BVH.
    """
    if name_map is not None:
        our_index = {name: i for i, name in enumerate(our_names)}
        bvh_index = {name: i for i, name in enumerate(bvh_names)}
        unknown_ours = [name for name in name_map if name not in our_index]
        unknown_bvh = [name for name in name_map.values() if name not in bvh_index]
        if unknown_ours:
            raise BvhError(f"name_map names joints that are not in the skeleton: {unknown_ours}")
        if unknown_bvh:
            raise BvhError(f"name_map names joints that are not in the BVH: {unknown_bvh} "
                           f"(BVH joints: {bvh_names})")
        return {our_index[ours]: bvh_index[theirs] for ours, theirs in name_map.items()}

    def unique_index(keys: list[str]) -> dict[str, int]:
        seen: dict[str, int] = {}
        duplicated = set()
        for i, key in enumerate(keys):
            if key in seen:
                duplicated.add(key)
            seen[key] = i
        return {key: i for key, i in seen.items() if key not in duplicated}

    mapping: dict[int, int] = {}
    exact = unique_index([name.lower() for name in bvh_names])
    for i, name in enumerate(our_names):
        if name.lower() in exact:
            mapping[i] = exact[name.lower()]
    used = set(mapping.values())
    loose_bvh = unique_index([_alias_key(name) for name in bvh_names])
    loose_ours = unique_index([_alias_key(name) for name in our_names])
    for key, i in loose_ours.items():
        if i not in mapping and key in loose_bvh and loose_bvh[key] not in used:
            mapping[i] = loose_bvh[key]
            used.add(loose_bvh[key])
    return mapping


def _topological_order(parents: np.ndarray) -> list[int]:
    """Joint indices with every parent before its children; BvhError on cycles or bad indices."""
    joint_count = parents.shape[0]
    children: list[list[int]] = [[] for _ in range(joint_count)]
    roots = []
    for joint, parent in enumerate(parents):
        if parent < 0:
            roots.append(joint)
        elif parent >= joint_count:
            raise BvhError(f"skeleton joint {joint} has parent {parent} out of range")
        else:
            children[parent].append(joint)
    order, stack = [], list(reversed(roots))
    while stack:
        joint = stack.pop()
        order.append(joint)
        stack.extend(reversed(children[joint]))
    if len(order) != joint_count:
        raise BvhError("skeleton parents contain a cycle")
    return order


def retarget_bvh(bvh: BvhMotion, skeleton, *, name_map: dict | None = None, scale: float | None = None,
                 up=None) -> np.ndarray:
    """Bone transforms of our skeleton that follow a BVH motion.

    For each of our joints j mapped to a BVH joint b (see :func:`match_joint_names`), its rotation is b's
    world rotation relative to the BVH rest pose (where it is the identity), expressed in our frame:
    ``R_j = C @ R_world(b) @ C^T`` with ``C`` the rotation from the BVH up axis to ``skeleton.up``.
    An unmapped joint takes its parent's rotation (it stays in its rest pose relative to the parent; an
    unmapped root gets the identity). Heads follow the parent, so our bone lengths are kept:
    ``head_posed_j = B_parent @ [head_rest_j, 1]`` and ``B_j = [R_j | head_posed_j - R_j @ head_rest_j]``.
    A root's head moves by the BVH root's displacement from its rest position, ``C @ delta * scale``; the
    rest position is taken with the BVH rest pose standing on the floor (its lowest joint or End Site at
    up = 0), which is the OFFSET itself for files whose rest pose stands on the floor, and removes the hip
    height of files whose root OFFSET is zero.

    Args:
        bvh: the parsed motion.
        skeleton: our skeleton: ``names`` (J str), ``parents`` ([J] int, -1 for roots), ``heads`` [J,3],
            ``tails`` [J,3] and ``up`` [3] (e.g. ``warpavatar.data.Skeleton``).
        name_map: {our joint name: BVH joint name}; default: matching names (see match_joint_names).
        scale: skeleton units per BVH unit; default: the height of our rest skeleton (heads and tails
            along ``up``) over the height of the BVH rest pose (joints and End Sites).
        up: the BVH up axis, 'Y' (default), 'Z', '-Y', ... or a 3-vector.

    Returns:
        [T,J,4,4] float32 rigid bone transforms (rest pose -> posed world), as in ``poses.npz``.

    Raises:
        BvhError: no joint maps, unknown names in ``name_map``, degenerate heights, a bad skeleton.
    """
    names = [str(name) for name in skeleton.names]
    joint_count = len(names)
    parents = np.asarray(skeleton.parents).astype(np.int64).reshape(-1)
    heads = np.asarray(skeleton.heads, dtype=np.float64).reshape(-1, 3)
    tails = np.asarray(skeleton.tails, dtype=np.float64).reshape(-1, 3)
    if parents.shape[0] != joint_count or heads.shape[0] != joint_count or tails.shape[0] != joint_count:
        raise BvhError(f"skeleton arrays do not match its {joint_count} joint names")
    if not (np.isfinite(heads).all() and np.isfinite(tails).all()):
        raise BvhError("skeleton heads/tails hold non-finite values")
    order = _topological_order(parents)
    our_up = _axis_vector(np.asarray(skeleton.up, dtype=np.float64))
    bvh_up = _axis_vector("Y" if up is None else up)
    conversion = up_axis_rotation(bvh_up, our_up)

    mapping = match_joint_names(names, bvh.names, name_map)
    if not mapping:
        raise BvhError(f"{bvh.path}: no joint of the skeleton maps to a BVH joint; pass name_map "
                       f"(skeleton: {names[:8]}{'...' if joint_count > 8 else ''}; BVH: "
                       f"{bvh.names[:8]}{'...' if bvh.joint_count > 8 else ''})")

    rest_joints, rest_ends = bvh_rest_positions(bvh)
    rest_points = np.concatenate([rest_joints, rest_ends])
    heights = rest_points @ bvh_up
    if scale is None:
        ours = np.concatenate([heads, tails]) @ our_up
        bvh_height = heights.max() - heights.min()
        our_height = ours.max() - ours.min()
        if bvh_height <= 0 or our_height <= 0:
            raise BvhError(f"{bvh.path}: cannot infer the scale from rest heights (skeleton {our_height}, "
                           f"BVH {bvh_height}); pass bvh_scale")
        scale = our_height / bvh_height
    elif not (np.isfinite(scale) and scale > 0):
        raise BvhError(f"scale must be a finite number > 0, got {scale!r}")

    world_rotations, world_positions = bvh_forward_kinematics(bvh)
    frame_count = bvh.frame_count
    # Displacement of the (first) BVH root from its rest position placed on the floor.
    root = int(np.flatnonzero(bvh.parents < 0)[0])
    rest_root = rest_joints[root] - bvh_up * heights.min()
    root_delta = (world_positions[:, root] - rest_root) @ conversion.T * scale  # [T,3], our frame

    bones = np.zeros((frame_count, joint_count, 4, 4))
    bones[:, :, 3, 3] = 1.0
    for joint in order:
        parent = parents[joint]
        if joint in mapping:
            rotation = conversion @ world_rotations[:, mapping[joint]] @ conversion.T
        elif parent >= 0:
            rotation = bones[:, parent, :3, :3]
        else:
            rotation = np.broadcast_to(np.eye(3), (frame_count, 3, 3))
        if parent >= 0:
            head = np.einsum("tij,j->ti", bones[:, parent, :3, :3], heads[joint]) + bones[:, parent, :3, 3]
        else:
            head = heads[joint] + root_delta
        bones[:, joint, :3, :3] = rotation
        bones[:, joint, :3, 3] = head - np.einsum("tij,j->ti", rotation, heads[joint])
    return bones.astype(np.float32)
