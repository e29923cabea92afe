"""The avatar's skinned, textured mesh and its motion as glTF 2.0 (``.glb``, or ``.gltf`` with its buffer embedded).

What the file holds (core glTF 2.0, no extensions):

* one mesh with one triangle primitive: ``POSITION`` (with min/max), ``NORMAL``, ``TEXCOORD_0``, ``JOINTS_0``
  (unsigned short) and ``WEIGHTS_0`` (float), 16- or 32-bit indices; ``COLOR_0`` (normalized unsigned bytes)
  only when the mesh has vertex colours and no texture, as glTF multiplies ``COLOR_0`` into the base colour and
  the texture already holds the same colours;
* a PBR material: ``baseColorTexture`` (the atlas as an embedded PNG, linear filtering with mipmaps, clamped
  at the edges), metallic 0, roughness 1;
* the rig as a node hierarchy: each joint's rest local translation is its head minus its parent's, without
  rotation (rest joint frames are unrotated); a skin whose inverse bind matrices are ``translate(-head)``, with
  the rig's root as ``skeleton`` (a node named ``rig`` above the roots when the rig has several);
* the skinned mesh node at the scene's root, without a transform (the specification ignores it);
* an animation ``motion``: a translation and a rotation channel per joint, linear interpolation, input times
  ``(frame_id - first frame id) / fps``; the joint frame at frame t is ``joint_transforms[t, j] @
  translate(head_j)`` and its local transform ``inverse(parent frame) @ frame``, orthonormalised before it is
  written as a quaternion (x, y, z, w);
* where the animation has vertex offsets (cloth and secondary motion that skinning cannot make), morph targets
  (:func:`morph_targets`) and a ``weights`` channel keyed at every frame.

Why morph targets: they are core glTF's only vertex cache that players blend, and glTF applies them before
skinning, as the offsets are defined; a mesh per frame switched by visibility is no core feature players
interpolate. So the offsets are compressed into their uncentred principal components (zero weights give the rest
mesh), or kept as one target a frame where that needs no more targets. Why each component is split into a
positive and a negative target (weights ``max(c, 0)`` and ``max(-c, 0)``, each scaled into [0, 1]): players may
clamp weights to [0, 1] (Blender's importer clamps each shape key to [0, 1], widened only to the first keyframe's
weight); the difference of two linearly interpolated weights is the interpolated coefficient, so playback between
frames is unchanged. The tolerance: the fewest components whose largest error at any vertex and frame is at most
:data:`MORPH_TOLERANCE` (0.2 mm, twice :data:`warpavatar.mesh.skin.OFFSET_TOLERANCE`, below which no offsets are
written at all), at most :data:`MAX_MORPH_TARGETS` targets; where the cap stops short of it, :class:`GltfFile`
says so and :func:`write_gltf` warns. A target that moves at most :data:`SPARSE_SHARE` of the vertices (a
garment) is a sparse accessor (core glTF, read by Blender and three.js): its moving vertices' indices and values.

Axes: glTF is Y-up while the avatar's data has its skeleton's ``up`` (``+Z`` in the supplied data). Every
position, normal, offset and matrix is rotated to Y-up before it is written (the smallest rotation taking
``up`` to ``+Y``; for ``+Z`` the rotation of -90 degrees about X, which also takes a subject facing ``-Y`` to
glTF's front, ``+Z``), so that no node carries the conversion: the skinned mesh node must stay without a
transform, and joints under a rotated root would make every consumer compose it. Units are metres.
"""

from __future__ import annotations

import base64
import dataclasses
import json
import math
import struct
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from warpavatar import __version__
from warpavatar.io.output_files import write_bytes_atomic
from warpavatar.mesh.mesh_data import AvatarMesh, MeshAnimation

__all__ = ["GENERATOR", "MORPH_TOLERANCE", "MAX_MORPH_TARGETS", "SPARSE_SHARE", "GltfFile", "MorphTargets",
           "write_gltf", "check_mesh", "up_to_y_rotation", "morph_targets", "rotation_quaternions"]

GENERATOR = f"warpavatar {__version__}"
"""``asset.generator`` of the files written here."""

MORPH_TOLERANCE = 2e-4
"""Largest distance [m] between a vertex offset and its morph-target reconstruction, at any vertex and frame."""

MAX_MORPH_TARGETS = 64
"""Most morph targets written (Blender and three.js, which blends them from a texture, take any number; engines
that blend on fixed GPU slots may take fewer)."""

SPARSE_SHARE = 0.5
"""A morph target moving at most this share of the vertices is written as a sparse accessor."""

_BASIS_FRAMES = 512  # most frames (evenly spaced) the basis is computed from; every frame is projected on it
_STILL_SHARE = 0.01  # a vertex whose offset never exceeds this share of the tolerance is still (zero in every target)
_BLOCK_FRAMES = 64  # frames, and columns (3 a vertex), handled at once, to bound the memory of long motions
_BLOCK_COLUMNS = 3 * 16384

_FLOAT, _UNSIGNED_BYTE, _UNSIGNED_SHORT, _UNSIGNED_INT = 5126, 5121, 5123, 5125
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963
_LINEAR, _LINEAR_MIPMAP_LINEAR, _CLAMP_TO_EDGE = 9729, 9987, 33071
_GLB_MAGIC, _GLB_JSON, _GLB_BIN = 0x46546C67, 0x4E4F534A, 0x004E4942


@dataclass(frozen=True)
class GltfFile:
    """What :func:`write_gltf` wrote.

    Attributes:
        path: the file.
        byte_count: its size [bytes].
        binary: a ``.glb`` (True) or a ``.gltf`` with its buffer embedded (False).
        frame_count: frames of the animation (0 without one).
        morph_target_count: morph targets (0 without vertex offsets).
        morph_error_max: largest distance [m] between a vertex's offset and its reconstruction from the morph
            targets, over every frame (0 without).
        morph_error_rms: root mean square of that distance [m] over every vertex and frame.
        morph_within_tolerance: whether ``morph_error_max`` is at most the tolerance asked (False where the cap
            on the target count stopped short of it).
        morph_sparse_count: morph targets written as sparse accessors.
    """

    path: Path
    byte_count: int
    binary: bool
    frame_count: int
    morph_target_count: int
    morph_error_max: float
    morph_error_rms: float
    morph_within_tolerance: bool = True
    morph_sparse_count: int = 0


def up_to_y_rotation(up) -> np.ndarray:
    """The smallest rotation [3,3] (float64) taking the direction ``up`` [3] to ``+Y`` (glTF's up)."""
    up = np.asarray(up, dtype=np.float64).reshape(3)
    length = float(np.linalg.norm(up))
    if not math.isfinite(length) or length == 0.0:
        raise ValueError(f"the mesh's up direction must be a non-zero vector, got {up.tolist()}")
    a = up / length
    b = np.array([0.0, 1.0, 0.0])
    axis = np.cross(a, b)
    sine, cosine = float(np.linalg.norm(axis)), float(a @ b)
    if sine < 1e-12:
        return np.eye(3) if cosine > 0 else np.diag([1.0, -1.0, -1.0])  # half a turn about X
    k = axis / sine
    cross = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + sine * cross + (1.0 - cosine) * (cross @ cross)


def rotation_quaternions(matrices: np.ndarray) -> np.ndarray:
    """Unit quaternions [...,4] (x, y, z, w: glTF's order) of the rotations nearest to ``matrices`` [...,3,3].

    Each matrix is first replaced by its nearest rotation (the orthonormal polar factor, by SVD), so transforms
    that are rigid up to float rounding give exactly unit quaternions; ``w`` is made non-negative.
    """
    matrices = np.asarray(matrices, dtype=np.float64)
    u, _, vt = np.linalg.svd(matrices)
    flip = np.sign(np.linalg.det(u @ vt))
    u[..., :, 2] *= flip[..., None]
    r = u @ vt
    # Shepperd's method: the largest of (trace, diagonal) picks a well-conditioned formula
    trace = r[..., 0, 0] + r[..., 1, 1] + r[..., 2, 2]
    candidates = np.stack([trace, r[..., 0, 0], r[..., 1, 1], r[..., 2, 2]], axis=-1)
    pick = np.argmax(candidates, axis=-1)
    q = np.zeros(r.shape[:-2] + (4,))
    for case in range(4):
        m = pick == case
        if not m.any():
            continue
        rm = r[m]
        if case == 0:
            s = 2.0 * np.sqrt(1.0 + trace[m])
            q[m] = np.stack([(rm[:, 2, 1] - rm[:, 1, 2]) / s, (rm[:, 0, 2] - rm[:, 2, 0]) / s,
                             (rm[:, 1, 0] - rm[:, 0, 1]) / s, 0.25 * s], axis=-1)
        elif case == 1:
            s = 2.0 * np.sqrt(1.0 + rm[:, 0, 0] - rm[:, 1, 1] - rm[:, 2, 2])
            q[m] = np.stack([0.25 * s, (rm[:, 0, 1] + rm[:, 1, 0]) / s, (rm[:, 0, 2] + rm[:, 2, 0]) / s,
                             (rm[:, 2, 1] - rm[:, 1, 2]) / s], axis=-1)
        elif case == 2:
            s = 2.0 * np.sqrt(1.0 + rm[:, 1, 1] - rm[:, 0, 0] - rm[:, 2, 2])
            q[m] = np.stack([(rm[:, 0, 1] + rm[:, 1, 0]) / s, 0.25 * s, (rm[:, 1, 2] + rm[:, 2, 1]) / s,
                             (rm[:, 0, 2] - rm[:, 2, 0]) / s], axis=-1)
        else:
            s = 2.0 * np.sqrt(1.0 + rm[:, 2, 2] - rm[:, 0, 0] - rm[:, 1, 1])
            q[m] = np.stack([(rm[:, 0, 2] + rm[:, 2, 0]) / s, (rm[:, 1, 2] + rm[:, 2, 1]) / s, 0.25 * s,
                             (rm[:, 1, 0] - rm[:, 0, 1]) / s], axis=-1)
    q *= np.where(q[..., 3:] < 0, -1.0, 1.0)
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


@dataclass(frozen=True)
class MorphTargets:
    """Morph targets whose weighted sums give per-frame vertex offsets (see the module docstring).

    Attributes:
        targets: [K,V,3] float32 displacements [m]; most are zero outside the vertices that move.
        weights: [T,K] float32 weights, each in [0, 1]: offsets[t] ~ sum_k weights[t, k] targets[k].
        names: K names: ``offset_component_{k}_positive`` / ``_negative`` (the two signs of principal component
            k), or ``offset_frame_{t}`` (row t of the offsets, one target a frame).
        error_max: largest distance [m] between a vertex's offset and its reconstruction, over every frame.
        error_rms: root mean square of that distance [m] over every vertex and frame.
        within_tolerance: whether ``error_max`` is at most the tolerance asked (False where the cap on the target
            count stopped short of it).
    """

    targets: np.ndarray
    weights: np.ndarray
    names: list[str]
    error_max: float
    error_rms: float
    within_tolerance: bool

    @property
    def count(self) -> int:
        return int(self.targets.shape[0])


def morph_targets(offsets: np.ndarray, *, tolerance: float = MORPH_TOLERANCE,
                  max_targets: int = MAX_MORPH_TARGETS) -> MorphTargets:
    """The fewest morph targets (at most ``max_targets``) with weights in [0, 1] that reproduce per-frame vertex
    offsets within ``tolerance`` at every vertex and frame.

    Two candidates: the uncentred principal components of the offsets, each split into a positive and a negative
    target (one where its coefficients keep one sign), the fewest whose largest error is within ``tolerance``
    (found by bisection); or one target a frame with offsets (exact), where that is no more targets. Vertices whose
    offset never exceeds a hundredth of ``tolerance`` are taken as still (zero in every target).

    Args:
        offsets: [T,V,3] offsets [m].
        tolerance: largest distance [m] allowed between an offset and its reconstruction.
        max_targets: most targets (at least 2); where they cannot reach ``tolerance``, the components that fit
            are kept and ``within_tolerance`` is False.

    Returns:
        a :class:`MorphTargets` (no targets for all-zero offsets).
    """
    offsets = np.asarray(offsets, dtype=np.float32)
    if offsets.ndim != 3 or offsets.shape[2] != 3:
        raise ValueError(f"offsets must have shape [T, V, 3], got {list(offsets.shape)}")
    if not (math.isfinite(tolerance) and tolerance > 0.0) or int(max_targets) < 2:
        raise ValueError(f"the morph tolerance must be a positive number of metres and the most morph targets at "
                         f"least 2 (one component's two signs), got {tolerance} and {max_targets}")
    if not np.isfinite(offsets).all():
        raise ValueError("the animation's vertex offsets are not all finite")
    max_targets = int(max_targets)
    frame_count, vertex_count = offsets.shape[:2]
    largest = np.zeros(vertex_count, np.float32)
    for start in range(0, frame_count, _BLOCK_FRAMES):
        np.maximum(largest, _vertex_norms(offsets[start:start + _BLOCK_FRAMES]).max(0), out=largest)
    moving = np.flatnonzero(largest > _STILL_SHARE * tolerance)
    # [T, 3M]: the vertices that move
    rows = offsets.reshape(frame_count, -1) if moving.size == vertex_count else \
        offsets[:, moving].reshape(frame_count, -1)
    frames = np.flatnonzero(np.abs(rows).max(1, initial=0.0) > 0.0)
    if frames.size == 0:
        empty = MorphTargets(np.zeros((0, vertex_count, 3), np.float32), np.zeros((frame_count, 0), np.float32),
                             [], 0.0, 0.0, True)
        return dataclasses.replace(empty, **_errors_of(offsets, empty, tolerance))
    components = _split_components(rows, tolerance, min(max_targets, frames.size - 1))
    if components is not None and (components[3] or frames.size > max_targets):
        basis, weights, names, _ = components
    else:  # one target a frame: no more targets than the components need, and exact
        basis = rows[frames].astype(np.float32)
        weights = np.zeros((frame_count, frames.size), np.float32)
        weights[frames, np.arange(frames.size)] = 1.0
        names = [f"offset_frame_{t}" for t in frames.tolist()]
    targets = np.zeros((basis.shape[0], vertex_count, 3), np.float32)
    targets[:, moving] = basis.reshape(basis.shape[0], moving.size, 3)
    result = MorphTargets(targets, weights, names, 0.0, 0.0, True)
    return dataclasses.replace(result, **_errors_of(offsets, result, tolerance))


def _vertex_norms(offsets: np.ndarray) -> np.ndarray:
    """Per-vertex lengths [T,V] of offsets [T,V,3]."""
    return np.sqrt(np.einsum("tvc,tvc->tv", offsets, offsets))


def _split_components(rows: np.ndarray, tolerance: float, limit: int):
    """The principal components of ``rows`` [T,3M] split by sign: ``(basis [K,3M] float32, weights [T,K] float32
    in [0, 1], names, within tolerance)`` for the fewest components within ``tolerance`` (else the most whose
    targets number at most ``limit``); None where ``limit`` allows no target."""
    if limit < 1:
        return None
    frame_count = rows.shape[0]
    sample = np.unique(np.linspace(0, frame_count - 1, min(frame_count, _BASIS_FRAMES)).round().astype(int))
    gram = np.zeros((sample.size, sample.size))  # [S,S]: the components from the small side of the SVD
    for start in range(0, rows.shape[1], _BLOCK_COLUMNS):
        chosen = rows[sample, start:start + _BLOCK_COLUMNS].astype(np.float64)
        gram += chosen @ chosen.T
    values, vectors = np.linalg.eigh(gram)
    order = np.argsort(values)[::-1]
    values, vectors = values[order], vectors[:, order]
    count = min(limit, int((values > values[0] * 1e-12).sum()))
    basis = np.empty((count, rows.shape[1]))  # orthonormal rows
    for start in range(0, rows.shape[1], _BLOCK_COLUMNS):
        chosen = rows[sample, start:start + _BLOCK_COLUMNS].astype(np.float64)
        basis[:, start:start + _BLOCK_COLUMNS] = vectors[:, :count].T @ chosen
    basis /= np.sqrt(values[:count])[:, None]
    coefficients = np.concatenate([rows[start:start + _BLOCK_FRAMES].astype(np.float64) @ basis.T
                                   for start in range(0, frame_count, _BLOCK_FRAMES)])  # [T,K]
    # each sign of a component is a target, but for a sign whose largest displacement is below the still share
    peak = np.sqrt(np.square(basis.reshape(count, -1, 3)).sum(-1)).max(1)  # [K] largest vertex length
    positive, negative = coefficients.clip(0.0, None).max(0), (-coefficients).clip(0.0, None).max(0)
    keep_positive = positive * peak > _STILL_SHARE * tolerance
    keep_negative = negative * peak > _STILL_SHARE * tolerance
    coefficients = np.where(keep_positive, coefficients, coefficients.clip(None, 0.0))
    coefficients = np.where(keep_negative, coefficients, coefficients.clip(0.0, None))
    sides = np.cumsum(keep_positive.astype(int) + keep_negative.astype(int))  # targets of the first k + 1
    fitting = int(np.searchsorted(sides, limit, side="right"))  # most components whose targets fit the limit
    if fitting == 0:
        return None
    basis32, coefficients32 = basis[:fitting].astype(np.float32), coefficients[:, :fitting].astype(np.float32)

    def error(kept: int) -> float:
        largest = 0.0
        for start in range(0, frame_count, _BLOCK_FRAMES):
            residual = rows[start:start + _BLOCK_FRAMES] - coefficients32[start:start + _BLOCK_FRAMES, :kept] \
                @ basis32[:kept]
            largest = max(largest, float(_vertex_norms(residual.reshape(residual.shape[0], -1, 3)).max()))
        return largest

    within = error(fitting) <= tolerance
    kept = fitting
    if within:  # bisect for the fewest components within the tolerance (the error falls with the count)
        low, high = 0, fitting  # error(low) > tolerance (or low is 0), error(high) <= tolerance
        while high - low > 1:
            middle = (low + high) // 2
            low, high = (low, middle) if error(middle) <= tolerance else (middle, high)
        kept = high
    targets, weights, names = [], [], []
    for k in range(kept):
        for sign, keep, scale, side in ((1.0, keep_positive[k], positive[k], "positive"),
                                        (-1.0, keep_negative[k], negative[k], "negative")):
            if keep:
                targets.append(basis[k] * (sign * scale))
                weights.append((sign * coefficients[:, k] / scale).clip(0.0, 1.0))
                names.append(f"offset_component_{k}_{side}")
    return (np.stack(targets).astype(np.float32), np.stack(weights, 1).astype(np.float32), names, within)


def _errors_of(offsets: np.ndarray, morph: MorphTargets, tolerance: float) -> dict:
    """``error_max``, ``error_rms`` and ``within_tolerance`` of ``morph``'s float32 targets and weights against
    the offsets [T,V,3]."""
    largest, total = 0.0, 0.0
    flat = morph.targets.reshape(morph.count, offsets.shape[1] * 3).astype(np.float64)
    for start in range(0, offsets.shape[0], _BLOCK_FRAMES):
        block = offsets[start:start + _BLOCK_FRAMES].astype(np.float64)
        rebuilt = (morph.weights[start:start + _BLOCK_FRAMES].astype(np.float64) @ flat).reshape(block.shape)
        distance = np.linalg.norm(block - rebuilt, axis=-1)
        largest = max(largest, float(distance.max(initial=0.0)))
        total += float(np.square(distance).sum())
    rms = math.sqrt(total / max(1, offsets.shape[0] * offsets.shape[1]))
    return {"error_max": largest, "error_rms": rms, "within_tolerance": largest <= tolerance}


# ------------------------------------------------------------------------------------------------ the writer
class _Builder:
    """The JSON document and its one binary buffer, grown view by view (each view 4-byte aligned)."""

    def __init__(self):
        self.chunks: list[bytes] = []
        self.size = 0
        self.doc: dict = {"asset": {"version": "2.0", "generator": GENERATOR}, "bufferViews": [], "accessors": []}

    def view(self, data: bytes, *, target: int | None = None) -> int:
        padding = (-self.size) % 4
        if padding:
            self.chunks.append(b"\0" * padding)
            self.size += padding
        entry = {"buffer": 0, "byteOffset": self.size, "byteLength": len(data)}
        if target is not None:
            entry["target"] = target
        self.chunks.append(data)
        self.size += len(data)
        self.doc["bufferViews"].append(entry)
        return len(self.doc["bufferViews"]) - 1

    def accessor(self, array: np.ndarray, kind: str, *, target: int | None = None, normalized: bool = False,
                 bounds: bool = False) -> int:
        component = {np.dtype(np.float32): _FLOAT, np.dtype(np.uint8): _UNSIGNED_BYTE,
                     np.dtype(np.uint16): _UNSIGNED_SHORT, np.dtype(np.uint32): _UNSIGNED_INT}[array.dtype]
        array = np.ascontiguousarray(array)
        width = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}[kind]
        count = array.size // width
        entry = {"bufferView": self.view(array.tobytes(), target=target), "componentType": component,
                 "count": int(count), "type": kind}
        if normalized:
            entry["normalized"] = True
        if bounds:
            flat = array.reshape(count, width)
            cast = float if array.dtype == np.float32 else int
            entry["min"] = [cast(v) for v in flat.min(0)]
            entry["max"] = [cast(v) for v in flat.max(0)]
        self.doc["accessors"].append(entry)
        return len(self.doc["accessors"]) - 1

    def sparse_accessor(self, array: np.ndarray) -> int:
        """A float32 VEC3 accessor of ``array`` [N,3] holding only its non-zero rows (zero elsewhere)."""
        array = np.ascontiguousarray(array, dtype=np.float32)
        rows = np.flatnonzero(np.any(array != 0.0, axis=1))
        index_type, index_component = ((np.uint16, _UNSIGNED_SHORT) if array.shape[0] <= 65536
                                       else (np.uint32, _UNSIGNED_INT))
        sparse = {"count": int(rows.size),
                  "indices": {"bufferView": self.view(rows.astype(index_type).tobytes()),
                              "componentType": index_component},
                  "values": {"bufferView": self.view(array[rows].tobytes())}}
        self.doc["accessors"].append({"componentType": _FLOAT, "count": int(array.shape[0]), "type": "VEC3",
                                      "min": [float(v) for v in array.min(0)],
                                      "max": [float(v) for v in array.max(0)], "sparse": sparse})
        return len(self.doc["accessors"]) - 1

    def binary(self) -> bytes:
        data = b"".join(self.chunks)
        return data + b"\0" * ((-len(data)) % 4)


def _rotate_matrices(rotation: np.ndarray, matrices: np.ndarray) -> np.ndarray:
    """``C M C^T`` for 4x4 matrices [...,4,4] and the 3x3 rotation ``C`` (a change of world axes)."""
    c = np.eye(4)
    c[:3, :3] = rotation
    return c @ np.asarray(matrices, dtype=np.float64) @ c.T


def _translations(points: np.ndarray) -> np.ndarray:
    matrices = np.tile(np.eye(4), (points.shape[0], 1, 1))
    matrices[:, :3, 3] = points
    return matrices


def _rigid_inverse(matrices: np.ndarray) -> np.ndarray:
    inverse = np.zeros_like(matrices)
    rotation = np.swapaxes(matrices[..., :3, :3], -1, -2)
    inverse[..., :3, :3] = rotation
    inverse[..., :3, 3] = -np.einsum("...ij,...j->...i", rotation, matrices[..., :3, 3])
    inverse[..., 3, 3] = 1.0
    return inverse


def _unit_normals(normals: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    good = np.isfinite(length) & (length > 1e-12)
    unit = np.where(good, normals / np.where(good, length, 1.0), fallback[None])
    unit = unit.astype(np.float32)
    return unit / np.linalg.norm(unit, axis=1, keepdims=True)


def check_mesh(mesh: AvatarMesh, animation: MeshAnimation | None) -> None:
    """Raise ValueError, with a one-line message, where ``mesh`` or ``animation`` is not what the writers take:
    arrays of the documented shapes, faces indexing the vertices, a rig without cycles, an animation only for a
    skinned mesh, with strictly increasing frame ids, a positive fps and offsets of shape [T,V,3]."""
    vertices, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    count = vertices.shape[0] if vertices.ndim == 2 else 0
    if vertices.ndim != 2 or vertices.shape[1] != 3 or count == 0 or not np.isfinite(vertices).all():
        raise ValueError(f"the mesh's vertices must be a finite [V, 3] array with V >= 1, got {list(vertices.shape)}")
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.shape[0] == 0:
        raise ValueError(f"the mesh's faces must have shape [F, 3] with F >= 1, got {list(faces.shape)}")
    if int(faces.min()) < 0 or int(faces.max()) >= count:
        raise ValueError(f"the mesh's faces must index its {count} vertices")
    for name, width in (("normals", 3), ("uvs", 2), ("vertex_colors", 3), ("joint_indices", 4),
                        ("joint_weights", 4)):
        value = getattr(mesh, name)
        if value is not None and np.asarray(value).shape != (count, width):
            raise ValueError(f"the mesh's {name} must have shape [{count}, {width}], got "
                             f"{list(np.asarray(value).shape)}")
    if mesh.texture is not None:
        texture = np.asarray(mesh.texture)
        if texture.ndim != 3 or texture.shape[2] != 3 or texture.dtype != np.uint8 or min(texture.shape[:2]) == 0:
            raise ValueError(f"the mesh's texture must be a [S, S, 3] uint8 image, got {texture.dtype} "
                             f"{list(texture.shape)}")
    skinned = mesh.joint_indices is not None
    if skinned:
        if mesh.joint_weights is None or mesh.joint_names is None or mesh.joint_parents is None \
                or mesh.joint_heads is None:
            raise ValueError("a skinned mesh needs joint_weights, joint_names, joint_parents and joint_heads")
        joint_count = len(mesh.joint_names)
        if joint_count > 65536 or int(np.asarray(mesh.joint_indices).max()) >= joint_count \
                or int(np.asarray(mesh.joint_indices).min()) < 0:
            raise ValueError(f"the mesh's joint indices must lie in 0..{joint_count - 1}")
        parents = np.asarray(mesh.joint_parents)
        if parents.shape != (joint_count,) or np.asarray(mesh.joint_heads).shape != (joint_count, 3):
            raise ValueError(f"the mesh's rig needs parents [{joint_count}] and heads [{joint_count}, 3]")
        for joint, parent in enumerate(parents.tolist()):
            if not -1 <= parent < joint_count or parent == joint:
                raise ValueError(f"the mesh's rig: joint {mesh.joint_names[joint]!r} has parent {parent}")
        _joint_order(parents)  # raises on a cycle
    if animation is None:
        return
    if not skinned:
        raise ValueError("an animation needs a skinned mesh (run warpavatar.mesh.skin.skin_mesh first)")
    transforms = np.asarray(animation.joint_transforms)
    frame_count = transforms.shape[0] if transforms.ndim == 4 else 0
    if transforms.shape != (frame_count, len(mesh.joint_names), 4, 4) or frame_count == 0:
        raise ValueError(f"the animation's joint transforms must have shape [T, {len(mesh.joint_names)}, 4, 4] "
                         f"with T >= 1, got {list(transforms.shape)}")
    if not np.isfinite(transforms).all():
        raise ValueError("the animation's joint transforms are not all finite")
    frame_ids = np.asarray(animation.frame_ids).reshape(-1)
    if frame_ids.shape != (frame_count,):
        raise ValueError(f"the animation has {frame_count} frames but {frame_ids.shape[0]} frame ids")
    if frame_count > 1 and bool((np.diff(frame_ids.astype(np.int64)) <= 0).any()):
        raise ValueError("the animation's frame ids must be strictly increasing")
    if not (math.isfinite(animation.fps) and animation.fps > 0):
        raise ValueError(f"the animation's fps must be a positive number, got {animation.fps}")
    if animation.vertex_offsets is not None:
        shape = np.asarray(animation.vertex_offsets).shape
        if shape != (frame_count, count, 3):
            raise ValueError(f"the animation's vertex offsets must have shape [{frame_count}, {count}, 3], "
                             f"got {list(shape)}")


def _joint_order(parents: np.ndarray) -> list[int]:
    """The joints, each after its parent (raises on a cycle)."""
    order, placed = [], np.zeros(len(parents), bool)
    while len(order) < len(parents):
        ready = [j for j in range(len(parents)) if not placed[j] and (parents[j] < 0 or placed[parents[j]])]
        if not ready:
            raise ValueError("the mesh's rig has a cycle in its joint parents")
        for j in ready:
            placed[j] = True
        order.extend(ready)
    return order


def _encode_png(texture: np.ndarray) -> bytes:
    import cv2

    ok, encoded = cv2.imencode(".png", np.ascontiguousarray(texture[:, :, ::-1]))
    if not ok:
        raise ValueError("the mesh's texture could not be encoded as PNG")
    return encoded.tobytes()


def write_gltf(path, mesh: AvatarMesh, animation: MeshAnimation | None = None, *, binary: bool | None = None,
               vertex_colors: bool | None = None, morph_tolerance: float = MORPH_TOLERANCE,
               max_morph_targets: int = MAX_MORPH_TARGETS) -> GltfFile:
    """Write a mesh, and optionally its animation, as glTF 2.0 (see the module docstring), atomically.

    Args:
        path: the output file (``.glb`` or ``.gltf``).
        mesh: the canonical mesh; skinned (:func:`warpavatar.mesh.skin.skin_mesh`) for a rig and an animation.
        animation: the motion (:func:`warpavatar.mesh.skin.mesh_animation`), or None for the rest pose.
        binary: write a ``.glb`` (True) or a ``.gltf`` with the buffer embedded as a ``data:`` URI (False);
            None: by the suffix (``.glb`` binary, anything else JSON).
        vertex_colors: write ``COLOR_0``; None: only when the mesh has vertex colours but no texture (glTF
            multiplies the two).
        morph_tolerance, max_morph_targets: the largest error [m] and the most morph targets for the vertex
            offsets (:func:`morph_targets`); where the targets cannot reach the tolerance, a warning says so.

    Returns:
        a :class:`GltfFile` saying what was written.
    """
    path = Path(path)
    binary = path.suffix.lower() == ".glb" if binary is None else bool(binary)
    check_mesh(mesh, animation)
    axes = up_to_y_rotation(mesh.up)
    builder = _Builder()
    doc = builder.doc

    vertices = (np.asarray(mesh.vertices, dtype=np.float64) @ axes.T).astype(np.float32)
    fallback = np.array([0.0, 1.0, 0.0])
    normals = _unit_normals(np.asarray(mesh.normals, dtype=np.float64) @ axes.T, fallback)
    attributes = {"POSITION": builder.accessor(vertices, "VEC3", target=_ARRAY_BUFFER, bounds=True),
                  "NORMAL": builder.accessor(normals, "VEC3", target=_ARRAY_BUFFER)}
    if mesh.uvs is not None:
        attributes["TEXCOORD_0"] = builder.accessor(np.asarray(mesh.uvs, dtype=np.float32), "VEC2",
                                                    target=_ARRAY_BUFFER)
    if vertex_colors is None:
        vertex_colors = mesh.vertex_colors is not None and mesh.texture is None
    if vertex_colors and mesh.vertex_colors is not None:
        rgba = np.full((mesh.vertex_count, 4), 255, np.uint8)
        rgba[:, :3] = np.asarray(mesh.vertex_colors, dtype=np.uint8)
        attributes["COLOR_0"] = builder.accessor(rgba, "VEC4", target=_ARRAY_BUFFER, normalized=True)
    skinned = mesh.joint_indices is not None
    if skinned:
        attributes["JOINTS_0"] = builder.accessor(np.asarray(mesh.joint_indices).astype(np.uint16), "VEC4",
                                                  target=_ARRAY_BUFFER)
        attributes["WEIGHTS_0"] = builder.accessor(np.asarray(mesh.joint_weights, dtype=np.float32), "VEC4",
                                                   target=_ARRAY_BUFFER)
    faces = np.asarray(mesh.faces)
    index_type = np.uint16 if mesh.vertex_count <= 65535 else np.uint32
    primitive = {"attributes": attributes,
                 "indices": builder.accessor(faces.astype(index_type).reshape(-1), "SCALAR",
                                             target=_ELEMENT_ARRAY_BUFFER),
                 "mode": 4, "material": 0}
    pbr = {"baseColorFactor": [1.0, 1.0, 1.0, 1.0], "metallicFactor": 0.0, "roughnessFactor": 1.0}
    if mesh.texture is not None and mesh.uvs is not None:
        image = builder.view(_encode_png(np.asarray(mesh.texture)))
        doc["images"] = [{"bufferView": image, "mimeType": "image/png", "name": "texture"}]
        doc["samplers"] = [{"magFilter": _LINEAR, "minFilter": _LINEAR_MIPMAP_LINEAR, "wrapS": _CLAMP_TO_EDGE,
                            "wrapT": _CLAMP_TO_EDGE}]
        doc["textures"] = [{"sampler": 0, "source": 0}]
        pbr["baseColorTexture"] = {"index": 0, "texCoord": 0}
    doc["materials"] = [{"name": "avatar", "pbrMetallicRoughness": pbr}]
    mesh_entry = {"name": "avatar", "primitives": [primitive]}
    doc["meshes"] = [mesh_entry]
    mesh_node = {"name": "avatar", "mesh": 0}
    nodes = [mesh_node]
    scene_nodes = [0]

    written_morph = None
    if skinned:
        heads = np.asarray(mesh.joint_heads, dtype=np.float64) @ axes.T
        parents = np.asarray(mesh.joint_parents, dtype=np.int64)
        first = len(nodes)
        for joint, name in enumerate(mesh.joint_names):
            parent = parents[joint]
            local = heads[joint] - (heads[parent] if parent >= 0 else 0.0)
            node = {"name": str(name)}
            if np.any(local != 0):
                node["translation"] = [float(v) for v in local.astype(np.float32)]
            nodes.append(node)
        for joint, parent in enumerate(parents.tolist()):
            if parent >= 0:
                nodes[first + parent].setdefault("children", []).append(first + joint)
        roots = [first + j for j in range(len(parents)) if parents[j] < 0]
        if len(roots) == 1:
            skeleton_root = roots[0]
        else:  # a common parent, so that the skin has one skeleton root
            nodes.append({"name": "rig", "children": roots})
            skeleton_root = len(nodes) - 1
        scene_nodes.append(skeleton_root)
        inverse_bind = _translations(-heads).astype(np.float32)
        doc["skins"] = [{"name": "rig", "skeleton": skeleton_root,
                         "joints": [first + j for j in range(len(parents))],
                         "inverseBindMatrices": builder.accessor(np.swapaxes(inverse_bind, 1, 2).reshape(-1, 16),
                                                                 "MAT4")}]
        mesh_node["skin"] = 0
        if animation is not None:
            written_morph = _write_animation(builder, mesh, animation, axes, heads, parents, first, mesh_entry,
                                             morph_tolerance=morph_tolerance, max_targets=max_morph_targets)
    doc["nodes"] = nodes
    doc["scenes"] = [{"name": "avatar", "nodes": scene_nodes}]
    doc["scene"] = 0

    data = builder.binary()
    doc["buffers"] = [{"byteLength": len(data)}]
    if binary:
        text = json.dumps(doc, separators=(",", ":")).encode("utf-8")
        text += b" " * ((-len(text)) % 4)
        total = 12 + 8 + len(text) + 8 + len(data)
        payload = b"".join([struct.pack("<III", _GLB_MAGIC, 2, total), struct.pack("<II", len(text), _GLB_JSON),
                            text, struct.pack("<II", len(data), _GLB_BIN), data])
    else:
        doc["buffers"][0]["uri"] = "data:application/octet-stream;base64," + base64.b64encode(data).decode("ascii")
        payload = (json.dumps(doc, indent=1) + "\n").encode("utf-8")
    write_bytes_atomic(path, payload)
    frame_count = 0 if animation is None else animation.frame_count
    if written_morph is None:
        return GltfFile(path=path, byte_count=len(payload), binary=binary, frame_count=frame_count,
                        morph_target_count=0, morph_error_max=0.0, morph_error_rms=0.0)
    morph, sparse_count = written_morph
    if not morph.within_tolerance:
        warnings.warn(f"{path}: {morph.count} morph targets (at most {max_morph_targets}) leave the vertex "
                      f"offsets up to {morph.error_max * 1000:.2f} mm off, more than the "
                      f"{morph_tolerance * 1000:.2f} mm tolerance", stacklevel=2)
    return GltfFile(path=path, byte_count=len(payload), binary=binary, frame_count=frame_count,
                    morph_target_count=morph.count, morph_error_max=morph.error_max,
                    morph_error_rms=morph.error_rms, morph_within_tolerance=morph.within_tolerance,
                    morph_sparse_count=sparse_count)


def _write_animation(builder: _Builder, mesh: AvatarMesh, animation: MeshAnimation, axes: np.ndarray,
                     heads: np.ndarray, parents: np.ndarray, first: int, mesh_entry: dict, *,
                     morph_tolerance: float, max_targets: int) -> tuple[MorphTargets, int] | None:
    """Add the animation (and the morph targets of its vertex offsets); returns the morph targets and how many
    are sparse, or None without offsets."""
    doc = builder.doc
    frame_ids = np.asarray(animation.frame_ids, dtype=np.int64).reshape(-1)
    times = ((frame_ids - frame_ids[0]) / float(animation.fps)).astype(np.float32)
    if times.shape[0] > 1 and bool((np.diff(times) <= 0).any()):
        raise ValueError("the animation's frame times are not strictly increasing in float32 (too many frames "
                         "for its fps)")
    time_accessor = builder.accessor(times, "SCALAR", bounds=True)
    transforms = _rotate_matrices(axes, animation.joint_transforms)  # [T,J,4,4] Y-up
    world = transforms @ _translations(heads)[None]  # posed joint frames
    local = world.copy()
    has_parent = parents >= 0
    local[:, has_parent] = _rigid_inverse(world[:, parents[has_parent]]) @ world[:, has_parent]
    rotations = rotation_quaternions(local[..., :3, :3])  # [T,J,4] x,y,z,w
    for t in range(1, rotations.shape[0]):  # the same hemisphere as the frame before: linear blends go the short way
        flip = (rotations[t] * rotations[t - 1]).sum(-1) < 0
        rotations[t, flip] *= -1.0
    translations = local[..., :3, 3]
    samplers, channels = [], []
    for joint in range(len(parents)):
        for kind, values in (("translation", translations[:, joint].astype(np.float32)),
                             ("rotation", rotations[:, joint].astype(np.float32))):
            output = builder.accessor(values, "VEC3" if kind == "translation" else "VEC4")
            samplers.append({"input": time_accessor, "output": output, "interpolation": "LINEAR"})
            channels.append({"sampler": len(samplers) - 1, "target": {"node": first + joint, "path": kind}})
    result = None
    if animation.vertex_offsets is not None:
        offsets = np.asarray(animation.vertex_offsets, dtype=np.float32) @ axes.T.astype(np.float32)
        morph = morph_targets(offsets, tolerance=morph_tolerance, max_targets=max_targets)
        sparse_count = 0
        if morph.count:
            accessors = []
            for target in morph.targets:
                if 0 < np.any(target != 0.0, axis=1).sum() <= SPARSE_SHARE * target.shape[0]:
                    accessors.append(builder.sparse_accessor(target))
                    sparse_count += 1
                else:
                    accessors.append(builder.accessor(target, "VEC3", target=_ARRAY_BUFFER, bounds=True))
            primitive = mesh_entry["primitives"][0]
            primitive["targets"] = [{"POSITION": index} for index in accessors]
            mesh_entry["weights"] = [0.0] * morph.count
            mesh_entry["extras"] = {"targetNames": list(morph.names)}
            samplers.append({"input": time_accessor, "output": builder.accessor(morph.weights.reshape(-1), "SCALAR"),
                             "interpolation": "LINEAR"})
            channels.append({"sampler": len(samplers) - 1, "target": {"node": 0, "path": "weights"}})
        result = (morph, sparse_count)
    doc["animations"] = [{"name": "motion", "samplers": samplers, "channels": channels,
                          "extras": {"frame_ids": frame_ids.tolist(), "fps": float(animation.fps)}}]
    return result
