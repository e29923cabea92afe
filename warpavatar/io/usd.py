"""Animated 3D Gaussians as OpenUSD: a time-sampled ``.usdc`` that DCC tools and renderers open directly.

Two layouts of the Gaussians prim (``prim_path``, under an ``Xform`` that is the stage's default prim):

``"particlefield"``
    one ``UsdVol.ParticleField3DGaussianSplat`` (OpenUSD's 3DGS schema, in usd-core 26.11): time-sampled
    ``positions``, ``orientations`` and ``scales`` (linear standard deviations) and ``extent``; ``opacities``
    (linear), ``radiance:sphericalHarmonicsDegree`` and ``radiance:sphericalHarmonicsCoefficients`` authored
    once (all (d+1)^2 RGB coefficients of particle 0, then of particle 1, ...; 3DGS convention, colour =
    0.5 + SH evaluation), plus ``primvars:displayColor`` / ``primvars:displayOpacity`` for viewers without
    splat support.
``"points"``
    a ``UsdGeom.Points`` fallback for tools that predate the schema: time-sampled ``points``, ``widths``
    (``2 * max(scale)``: the 1-sigma diameter along the longest axis), ``extent``, and primvars
    ``orientations`` (quatf), ``scales`` (float3); ``displayColor`` (the SH DC term as RGB, clipped to 0..1),
    ``displayOpacity``, ``sphericalHarmonicsCoefficients`` (elementSize (d+1)^2) and
    ``sphericalHarmonicsDegree`` authored once.

Time-sampled attributes also carry a default (non-time-sampled) value equal to the first frame, for tools
that read the stage without a time. ``extent`` is the box of every Gaussian's 3-sigma ellipsoid (the schema
has no extent plug-in, so it is computed here). With a ``skeleton``, a ``UsdSkel`` rig is added beside the
Gaussians: ``<root>/Rig`` (SkelRoot) with ``Skeleton`` and ``Animation`` (SkelAnimation) whose skinning
transforms are exactly the bone transforms passed to :meth:`GaussianUsdWriter.write_frame`.

Triangle meshes that move with the Gaussians (a simulated garment sheet, :class:`AnimatedMesh`) are written
beside the Gaussians prim, as its siblings (``/Avatar/Garment``): a ``UsdGeom.Mesh`` with its faces (no
subdivision, double-sided), time-sampled ``points`` and ``extent`` at every frame the Gaussians have, and a
constant ``primvars:displayColor``; in the same stage units and up axis as the Gaussians.

Memory stays bounded for long animations: the stage is a ``.usdc`` layer on disk that is saved every few
frames; usd-core's crate writer appends the new samples to the file and drops them from memory, so the
resident size does not grow with the number of frames (see ``docs/export.md`` for measurements).
Conventions: quaternions are (w, x, y, z) in and out of this module (USD's ``Vt.QuatfArray`` rows are
(x, y, z, w): converted here); matrices are column-vector 4x4 (``p' = M @ [p, 1]``; USD's row-vector
matrices are their transposes).
"""

from __future__ import annotations

import dataclasses
import errno
import numbers
import os
import re
from collections.abc import Mapping, Sequence

import numpy as np
from pxr import Sdf, Tf, Usd, UsdGeom, UsdSkel, UsdVol, Vt

from warpavatar.geometry import SH_C0, quat_from_matrix
from warpavatar.io.output_files import disk_full_error, temporary_path
from warpavatar.io.ply import _check_array

__all__ = ["GaussianUsdWriter", "AnimatedMesh", "read_gaussian_usd", "gaussian_extent", "local_joint_transforms",
           "LAYOUTS"]

LAYOUTS = ("particlefield", "points")
"""Names of the Gaussians prim layouts :class:`GaussianUsdWriter` can write."""

_EXTENT_SIGMAS = 3.0
_FLUSH_BYTES = 64 * 2**20


def _save_error(path: str, error: Exception) -> OSError:
    """usd-core's multi-line ``Tf.ErrorException`` of a failed create or save as one line naming ``path``: a
    :class:`~warpavatar.io.output_files.DiskFullError` where the disk filled up."""
    text = str(error)
    for code in (errno.ENOSPC, errno.EDQUOT):
        if os.strerror(code) in text:
            return disk_full_error(path, code)
    messages = re.findall(r" : '(.*)'\s*$", text, flags=re.MULTILINE)
    reason = messages[0] if messages else " ".join(text.split())
    return OSError(f"{path}: USD cannot write the file ({reason})")


def gaussian_extent(positions: np.ndarray, orientations: np.ndarray, scales: np.ndarray,
                    *, sigmas: float = _EXTENT_SIGMAS) -> np.ndarray:
    """Axis-aligned box [2,3] (min row, max row) holding every Gaussian's ``sigmas``-sigma ellipsoid.

    Args:
        positions: [N,3] float32 centres.
        orientations: [N,4] float32 rotations (w, x, y, z), non-zero (normalized here).
        scales: [N,3] float32 linear radii (standard deviations) along the local axes.
        sigmas: how many standard deviations the box holds.

    The box of an ellipsoid with rotation R and radii r_k along its axes has half-size
    ``sqrt(sum_k (R_ik r_k)^2)`` along world axis i. An empty set gives a zero box at the origin.
    """
    if positions.shape[0] == 0:
        return np.zeros((2, 3), dtype=np.float32)
    # Contiguous [N] columns and no [N,3,3] temporaries: this runs once per exported frame (~3 ms for 40k).
    w, x, y, z = np.ascontiguousarray(orientations.T)
    radii_squared = np.ascontiguousarray((sigmas * scales.T) ** 2)
    xx, yy, zz = x * x, y * y, z * z
    two = 2.0 / (w * w + xx + yy + zz)  # normalizes the quaternion
    xy, xz, yz, wx, wy, wz = x * y, x * z, y * z, w * x, w * y, w * z
    rows = (
        (1 - two * (yy + zz), two * (xy - wz), two * (xz + wy)),
        (two * (xy + wz), 1 - two * (xx + zz), two * (yz - wx)),
        (two * (xz - wy), two * (yz + wx), 1 - two * (xx + yy)),
    )
    half = np.empty((3, positions.shape[0]), dtype=np.float32)
    for axis, (a, b, c) in enumerate(rows):
        half[axis] = np.sqrt(a * a * radii_squared[0] + b * b * radii_squared[1] + c * c * radii_squared[2])
    columns = positions.T
    return np.stack([(columns - half).min(axis=1), (columns + half).max(axis=1)]).astype(np.float32)


@dataclasses.dataclass(frozen=True, eq=False)
class AnimatedMesh:
    """A triangle mesh that :class:`GaussianUsdWriter` animates beside the Gaussians (its points every frame).

    Attributes:
        name: the prim's name, a USD identifier (``"Garment"``); the prim is a sibling of the Gaussians prim.
        faces: [F,3] int vertex ids of the triangles (counter-clockwise seen from the front: right-handed).
        vertex_count: V, the number of points every frame.
        display_color: [3] linear RGB in 0..1, the mesh's one ``displayColor``.
    """

    name: str
    faces: np.ndarray
    vertex_count: int
    display_color: tuple[float, float, float] = (0.5, 0.5, 0.5)


def _check_meshes(meshes, gaussians_path: Sdf.Path, with_rig: bool) -> list[tuple[AnimatedMesh, np.ndarray,
                                                                                     np.ndarray]]:
    """Each mesh with its faces [F,3] int32 and display colour [3] float32, checked."""
    if isinstance(meshes, (AnimatedMesh, str)) or not isinstance(meshes, Sequence):
        raise TypeError(f"meshes must be a sequence of AnimatedMesh, got {type(meshes).__name__}")
    taken = {gaussians_path.name} | ({"Rig"} if with_rig and gaussians_path.GetParentPath().IsRootPrimPath() else set())
    checked = []
    for mesh in meshes:
        if not isinstance(mesh, AnimatedMesh):
            raise TypeError(f"meshes must hold AnimatedMesh, got {type(mesh).__name__}")
        if not (isinstance(mesh.name, str) and Tf.IsValidIdentifier(mesh.name)):
            raise ValueError(f"mesh name must be a USD identifier (letters, digits, _), got {mesh.name!r}")
        if mesh.name in taken:
            raise ValueError(f"mesh name {mesh.name!r} is taken by another prim beside the Gaussians")
        taken.add(mesh.name)
        count = mesh.vertex_count
        if not isinstance(count, numbers.Integral) or count < 3:
            raise ValueError(f"mesh {mesh.name!r}: vertex_count must be an int >= 3, got {count!r}")
        faces = _to_int_faces(mesh.name, mesh.faces)
        if faces.shape[0] == 0 or faces.min() < 0 or faces.max() >= count:
            raise ValueError(f"mesh {mesh.name!r}: faces must be a non-empty [F,3] array of vertex ids in "
                             f"0..{count - 1}")
        color = _check_array(f"mesh {mesh.name!r} display_color", mesh.display_color, (3,))
        if not ((color >= 0) & (color <= 1)).all():
            raise ValueError(f"mesh {mesh.name!r}: display_color must be RGB in 0..1, got {color.tolist()}")
        checked.append((mesh, faces, color))
    return checked


def _to_int_faces(name: str, faces) -> np.ndarray:
    if hasattr(faces, "detach"):
        faces = faces.detach().cpu().numpy()
    faces = np.asarray(faces)
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.dtype.kind not in "iu":
        raise ValueError(f"mesh {name!r}: faces must be an int array of shape [F, 3], got {list(faces.shape)} "
                         f"{faces.dtype}")
    return np.ascontiguousarray(faces, dtype=np.int32)


def _skeleton_fields(skeleton) -> tuple[list[str], np.ndarray, np.ndarray]:
    """(names, parents [J] int, heads [J,3] float64) from a Skeleton-like object or a mapping."""
    def field(name):
        if isinstance(skeleton, dict):
            if name not in skeleton:
                raise TypeError(f"skeleton mapping needs key {name!r}")
            return skeleton[name]
        if not hasattr(skeleton, name):
            raise TypeError(f"skeleton must have attributes names, parents, heads (missing {name!r})")
        return getattr(skeleton, name)

    names = [str(name) for name in field("names")]
    joint_count = len(names)
    parents = np.asarray(field("parents"))
    if parents.shape != (joint_count,) or parents.dtype.kind not in "iu":
        raise ValueError(f"skeleton.parents must be an int array of shape [{joint_count}], got "
                         f"{list(parents.shape)} {parents.dtype}")
    parents = parents.astype(np.int64)
    heads = _check_array("skeleton.heads", field("heads"), (joint_count, 3), dtype=np.float64)
    if joint_count == 0:
        raise ValueError("skeleton has no joints")
    for joint, parent in enumerate(parents):
        if not -1 <= parent < joint:
            raise ValueError(f"skeleton joint {joint} ({names[joint]!r}) has parent {parent}: UsdSkel needs every "
                             f"parent listed before its children (-1 for a root)")
    if len(set(names)) != joint_count:
        raise ValueError("skeleton joint names must be unique")
    return names, parents, heads


def _joint_paths(names: list[str], parents: np.ndarray) -> list[str]:
    """UsdSkel joint paths ("hips/spine/chest") from names, made valid and unique among siblings."""
    paths: list[str] = []
    taken: set[str] = set()
    for joint, name in enumerate(names):
        stem = Tf.MakeValidIdentifier(name)
        prefix = "" if parents[joint] < 0 else paths[parents[joint]] + "/"
        candidate, suffix = prefix + stem, 1
        while candidate in taken:
            candidate, suffix = f"{prefix}{stem}_{suffix}", suffix + 1
        taken.add(candidate)
        paths.append(candidate)
    return paths


def _translation_matrices(offsets: np.ndarray) -> np.ndarray:
    """[J,3] offsets -> [J,4,4] column-convention translations."""
    out = np.tile(np.eye(4), (offsets.shape[0], 1, 1))
    out[:, :3, 3] = offsets
    return out


def _to_usd_matrices(matrices: np.ndarray) -> Vt.Matrix4dArray:
    """[J,4,4] column-convention matrices -> USD row-vector Matrix4dArray (transposes)."""
    return Vt.Matrix4dArray.FromNumpy(np.ascontiguousarray(np.swapaxes(matrices, -1, -2), dtype=np.float64))


def _from_usd_matrices(matrices) -> np.ndarray:
    return np.swapaxes(np.asarray(matrices, dtype=np.float64).reshape(-1, 4, 4), -1, -2)


def local_joint_transforms(joint_transforms, parents: np.ndarray, bind: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Skinning transforms -> UsdSkel joint-local transforms (what a ``SkelAnimation`` stores).

    Args:
        joint_transforms: [J,4,4] rigid bone transforms (rest pose -> posed world), column convention.
        parents: [J] int parent of each joint (-1 for a root), parents before children.
        bind: [J,4,4] world rest frames of the joints (the Skeleton's ``bindTransforms``), column convention.

    Returns:
        (translations [J,3], rotations [J,4] (x, y, z, w), USD's order) float32, each joint's posed frame in its
        parent's posed frame.

    Raises:
        ValueError: a shape other than [J,4,4], or a transform that is not rigid.
    """
    joint_count = parents.shape[0]
    bones = _check_array("joint_transforms", joint_transforms, (joint_count, 4, 4), dtype=np.float64)
    rotations = bones[:, :3, :3]
    error = np.abs(np.einsum("jki,jkl->jil", rotations, rotations) - np.eye(3)).max(axis=(1, 2))
    bad = np.flatnonzero((error > 1e-3) | (np.linalg.det(rotations) < 0)
                         | (np.abs(bones[:, 3] - [0, 0, 0, 1]).max(axis=1) > 1e-6))
    if bad.size:
        raise ValueError(f"joint_transforms must be rigid (rotation + translation); joint {int(bad[0])} is not")
    world = bones @ bind  # posed joint frames: the bone transform applied to the rest joint frame
    parent_world = np.where(parents[:, None, None] >= 0, world[np.maximum(parents, 0)], np.eye(4))
    # Rigid inverse of the parent frame, then local = parent^-1 @ world.
    inverse = np.zeros_like(parent_world)
    inverse[:, :3, :3] = np.swapaxes(parent_world[:, :3, :3], 1, 2)
    inverse[:, :3, 3] = -np.einsum("jki,jk->ji", parent_world[:, :3, :3], parent_world[:, :3, 3])
    inverse[:, 3, 3] = 1.0
    local = inverse @ world
    quats = quat_from_matrix(np.asarray(local[:, :3, :3], dtype=np.float64))
    return (np.ascontiguousarray(local[:, :3, 3], dtype=np.float32),
            np.ascontiguousarray(quats[:, [1, 2, 3, 0]], dtype=np.float32))


class GaussianUsdWriter:
    """Writes an animation of a fixed set of Gaussians to a ``.usdc`` file, one frame at a time.

    Use it as a context manager: on a clean exit the file is finished and renamed into place; if an
    exception escapes the ``with`` block, the temporary file is deleted and ``path`` is left untouched::

        with GaussianUsdWriter("avatar.usdc", gaussian_count=n, sh_degree=3, opacities=o, sh_coeffs=sh) as w:
            for t, (x, q, s) in enumerate(frames):
                w.write_frame(t, positions=x, orientations=q, scales=s)

    Until :meth:`close`, the data goes to a temporary file of its own in the same folder,
    ``<path without extension>.tmp-<pid>-<hex>.usdc`` (missing folders are created); a writer dropped without
    :meth:`close` deletes it. An error while saving (a full disk included) is one line naming ``path``.

    Args:
        path: destination, ending in ``.usdc`` or ``.usd`` (written in the binary crate format).
        layout: ``"particlefield"`` (UsdVol.ParticleField3DGaussianSplat) or ``"points"`` (UsdGeom.Points);
            see the module docstring.
        gaussian_count: N, the number of Gaussians in every frame.
        sh_degree: d, the SH degree of ``sh_coeffs`` (0..4).
        opacities: [N] float linear opacities in [0, 1], authored once.
        sh_coeffs: [N,(d+1)^2,3] float SH coefficients (3DGS convention), authored once.
        fps: frames (time codes) per second; sets ``timeCodesPerSecond`` and ``framesPerSecond``.
        up_axis: ``"Z"`` or ``"Y"``: the stage's ``upAxis`` (the data is written as given, not rotated).
        meters_per_unit: the stage's ``metersPerUnit`` (1.0 for data in metres).
        prim_path: absolute path of the Gaussians prim, at least two levels deep; its first component
            becomes an ``Xform`` set as the default prim.
        skeleton: optional rig to add as UsdSkel: an object with ``names`` (J str), ``parents`` ([J] int, -1
            for roots, parents before children) and ``heads`` ([J,3] rest joint positions), such as
            ``warpavatar.data.Skeleton``, or a dict with those keys. Rest joint frames are unrotated, at
            the heads.
        meshes: triangle meshes to animate beside the Gaussians (:class:`AnimatedMesh`, each a ``UsdGeom.Mesh``
            sibling of the Gaussians prim): :meth:`write_frame` then takes their points every frame.
        flush_every: save the file every this many frames (default: as many frames as fit in ~64 MiB).

    Raises:
        ValueError: bad path extension, layout, shapes, values, prim path or mesh.
        TypeError: non-numeric arrays, a malformed skeleton or meshes that are not :class:`AnimatedMesh`.
        OSError: the file cannot be created or saved (:class:`~warpavatar.io.output_files.DiskFullError` for a
            full disk), here or in :meth:`write_frame` and :meth:`close`; the temporary file is then removed.
    """

    def __init__(self, path: str | os.PathLike, *, layout: str = "particlefield", gaussian_count: int,
                 sh_degree: int, opacities, sh_coeffs, fps: float = 30.0, up_axis: str = "Z",
                 meters_per_unit: float = 1.0, prim_path: str = "/Avatar/Gaussians", skeleton=None,
                 meshes: Sequence[AnimatedMesh] = (), flush_every: int | None = None):
        path = os.fspath(path)
        extension = os.path.splitext(path)[1].lower()
        if extension not in (".usdc", ".usd"):
            raise ValueError(f"path must end in .usdc or .usd (binary crate format), got {path!r}")
        if layout not in LAYOUTS:
            raise ValueError(f"layout must be one of {LAYOUTS}, got {layout!r}")
        if not isinstance(gaussian_count, numbers.Integral) or gaussian_count < 0:
            raise ValueError(f"gaussian_count must be an int >= 0, got {gaussian_count!r}")
        if not isinstance(sh_degree, numbers.Integral) or not 0 <= sh_degree <= 4:
            raise ValueError(f"sh_degree must be an int in 0..4, got {sh_degree!r}")
        if not (isinstance(fps, numbers.Real) and np.isfinite(fps) and fps > 0):
            raise ValueError(f"fps must be a finite number > 0, got {fps!r}")
        if up_axis not in ("Y", "Z"):
            raise ValueError(f"up_axis must be 'Y' or 'Z', got {up_axis!r}")
        if not (isinstance(meters_per_unit, numbers.Real) and np.isfinite(meters_per_unit) and meters_per_unit > 0):
            raise ValueError(f"meters_per_unit must be a finite number > 0, got {meters_per_unit!r}")
        if not (isinstance(prim_path, str) and Sdf.Path.IsValidPathString(prim_path)):
            raise ValueError(f"prim_path must be a valid USD prim path, got {prim_path!r}")
        gaussians_path = Sdf.Path(prim_path)
        prefixes = gaussians_path.GetPrefixes()
        if not gaussians_path.IsAbsolutePath() or not gaussians_path.IsPrimPath() or len(prefixes) < 2:
            raise ValueError(f"prim_path must be an absolute prim path with at least two components "
                             f"(e.g. '/Avatar/Gaussians'), got {prim_path!r}")
        if flush_every is not None and (not isinstance(flush_every, numbers.Integral) or flush_every < 1):
            raise ValueError(f"flush_every must be an int >= 1, got {flush_every!r}")

        count = int(gaussian_count)
        coefficient_count = (int(sh_degree) + 1) ** 2
        opacities = _check_array("opacities", opacities, (count,))
        if count and not ((opacities >= 0) & (opacities <= 1)).all():
            raise ValueError(f"opacities must be linear values in [0, 1], got range "
                             f"[{opacities.min()}, {opacities.max()}]")
        sh_coeffs = _check_array("sh_coeffs", sh_coeffs, (count, coefficient_count, 3))
        skeleton_fields = _skeleton_fields(skeleton) if skeleton is not None else None
        checked_meshes = _check_meshes(meshes, gaussians_path, skeleton is not None)

        self.path = path
        self.layout = layout
        self.gaussian_count = count
        self.sh_degree = int(sh_degree)
        self.prim_path = prim_path
        self.temporary_path = os.fspath(temporary_path(path, suffix=".usdc"))
        frame_bytes = max(1, count * 4 * (3 + 4 + 3 + (1 if layout == "points" else 0))
                          + sum(mesh.vertex_count * 12 for mesh, _, _ in checked_meshes))
        self.flush_every = int(flush_every) if flush_every is not None else max(1, _FLUSH_BYTES // frame_bytes)
        self.time_codes: list[int] = []
        self._closed = False
        self._unsaved_frames = 0

        try:
            layer = Sdf.Layer.CreateNew(self.temporary_path)
        except Tf.ErrorException as error:
            if os.path.exists(self.temporary_path):
                os.remove(self.temporary_path)
            raise _save_error(path, error) from None
        if layer is None:  # pragma: no cover - usd-core raises instead in practice
            raise OSError(f"{path}: USD cannot create the file")
        try:
            self._layer = layer
            self._stage = Usd.Stage.Open(layer)
            self._author_header(prefixes, opacities, sh_coeffs, float(fps), up_axis, float(meters_per_unit))
            self._skeleton = None
            if skeleton_fields is not None:
                self._author_skeleton(prefixes[0], *skeleton_fields)
            self._author_meshes(gaussians_path.GetParentPath(), checked_meshes)
            self._save()
        except BaseException:
            self._discard()
            raise

    # -- authoring -------------------------------------------------------------------------------

    def _author_header(self, prefixes, opacities, sh_coeffs, fps, up_axis, meters_per_unit) -> None:
        stage = self._stage
        UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z if up_axis == "Z" else UsdGeom.Tokens.y)
        UsdGeom.SetStageMetersPerUnit(stage, meters_per_unit)
        stage.SetTimeCodesPerSecond(fps)
        stage.SetFramesPerSecond(fps)
        for prefix in prefixes[:-1]:
            UsdGeom.Xform.Define(stage, prefix)
        stage.SetDefaultPrim(stage.GetPrimAtPath(prefixes[0]))
        stage.GetRootLayer().customLayerData = {"creator": "warpavatar", "gaussianLayout": self.layout}

        coefficients = Vt.Vec3fArray.FromNumpy(sh_coeffs.reshape(-1, 3))
        colors = Vt.Vec3fArray.FromNumpy(np.clip(sh_coeffs[:, 0, :] * SH_C0 + 0.5, 0.0, 1.0).astype(np.float32))
        opacity_values = Vt.FloatArray.FromNumpy(opacities)
        element_size = (self.sh_degree + 1) ** 2
        if self.layout == "particlefield":
            gaussians = UsdVol.ParticleField3DGaussianSplat.Define(stage, self.prim_path)
            self._attributes = {
                "positions": gaussians.CreatePositionsAttr(),
                "orientations": gaussians.CreateOrientationsAttr(),
                "scales": gaussians.CreateScalesAttr(),
                "extent": gaussians.CreateExtentAttr(),
            }
            gaussians.CreateOpacitiesAttr(opacity_values)
            gaussians.CreateRadianceSphericalHarmonicsDegreeAttr(self.sh_degree)
            sh_attribute = gaussians.CreateRadianceSphericalHarmonicsCoefficientsAttr(coefficients)
            sh_attribute.SetMetadata("interpolation", UsdGeom.Tokens.vertex)
            sh_attribute.SetMetadata("elementSize", element_size)
            gaussians.CreateDisplayColorPrimvar(UsdGeom.Tokens.vertex).Set(colors)
            gaussians.CreateDisplayOpacityPrimvar(UsdGeom.Tokens.vertex).Set(opacity_values)
        else:
            points = UsdGeom.Points.Define(stage, self.prim_path)
            primvars = UsdGeom.PrimvarsAPI(points.GetPrim())
            orientations = primvars.CreatePrimvar("orientations", Sdf.ValueTypeNames.QuatfArray,
                                                  UsdGeom.Tokens.vertex)
            scales = primvars.CreatePrimvar("scales", Sdf.ValueTypeNames.Float3Array, UsdGeom.Tokens.vertex)
            widths = points.CreateWidthsAttr()
            points.SetWidthsInterpolation(UsdGeom.Tokens.vertex)
            self._attributes = {
                "positions": points.CreatePointsAttr(),
                "orientations": orientations.GetAttr(),
                "scales": scales.GetAttr(),
                "widths": widths,
                "extent": points.CreateExtentAttr(),
            }
            points.CreateDisplayColorPrimvar(UsdGeom.Tokens.vertex).Set(colors)
            points.CreateDisplayOpacityPrimvar(UsdGeom.Tokens.vertex).Set(opacity_values)
            primvars.CreatePrimvar("sphericalHarmonicsCoefficients", Sdf.ValueTypeNames.Float3Array,
                                   UsdGeom.Tokens.vertex, element_size).Set(coefficients)
            primvars.CreatePrimvar("sphericalHarmonicsDegree", Sdf.ValueTypeNames.Int,
                                   UsdGeom.Tokens.constant).Set(self.sh_degree)

    def _author_skeleton(self, root_path: Sdf.Path, names, parents, heads) -> None:
        stage = self._stage
        rig_path = root_path.AppendChild("Rig")
        if Sdf.Path(self.prim_path).HasPrefix(rig_path):
            raise ValueError(f"prim_path {self.prim_path!r} collides with the skeleton rig at {rig_path}")
        UsdSkel.Root.Define(stage, rig_path)
        skeleton = UsdSkel.Skeleton.Define(stage, rig_path.AppendChild("Skeleton"))
        animation = UsdSkel.Animation.Define(stage, rig_path.AppendChild("Animation"))
        joints = Vt.TokenArray(_joint_paths(names, parents))
        parent_heads = np.where(parents[:, None] >= 0, heads[np.maximum(parents, 0)], 0.0)
        bind = _translation_matrices(heads)
        skeleton.CreateJointsAttr(joints)
        skeleton.CreateJointNamesAttr(Vt.TokenArray(names))
        skeleton.CreateBindTransformsAttr(_to_usd_matrices(bind))
        skeleton.CreateRestTransformsAttr(_to_usd_matrices(_translation_matrices(heads - parent_heads)))
        animation.CreateJointsAttr(joints)
        animation.CreateScalesAttr(Vt.Vec3hArray.FromNumpy(np.ones((len(names), 3), dtype=np.float16)))
        self._skeleton_attributes = {
            "translations": animation.CreateTranslationsAttr(),
            "rotations": animation.CreateRotationsAttr(),
        }
        UsdSkel.BindingAPI.Apply(skeleton.GetPrim()).CreateAnimationSourceRel().SetTargets([animation.GetPath()])
        self._skeleton = (parents, heads, bind)

    def _author_meshes(self, parent: Sdf.Path, meshes) -> None:
        """One ``UsdGeom.Mesh`` under ``parent`` per checked mesh; keeps its points and extent attributes."""
        self._mesh_attributes: dict[str, tuple[int, Usd.Attribute, Usd.Attribute]] = {}
        for mesh, faces, color in meshes:
            prim = UsdGeom.Mesh.Define(self._stage, parent.AppendChild(mesh.name))
            prim.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(faces.shape[0], 3, dtype=np.int32)))
            prim.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(faces.reshape(-1)))
            prim.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)  # a triangle sheet, not a subdivision cage
            prim.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
            prim.CreateDoubleSidedAttr(True)  # a cloth sheet is seen from both sides
            prim.CreateDisplayColorPrimvar(UsdGeom.Tokens.constant).Set(Vt.Vec3fArray.FromNumpy(color[None]))
            self._mesh_attributes[mesh.name] = (int(mesh.vertex_count), prim.CreatePointsAttr(),
                                                prim.CreateExtentAttr())

    def _set(self, attribute: Usd.Attribute, value, time_code: int, first: bool) -> None:
        attribute.Set(value, Usd.TimeCode(time_code))
        if first:
            attribute.Set(value)  # default value = first frame

    def write_frame(self, time_code: int, *, positions, orientations, scales, joint_transforms=None,
                    mesh_points: Mapping[str, object] | None = None) -> None:
        """Author one frame of the animation.

        Args:
            time_code: the frame's time code (an int, larger than every earlier one; seconds =
                time_code / fps).
            positions: [N,3] float Gaussian centres, stage units.
            orientations: [N,4] float rotations (w, x, y, z), non-zero (stored as given).
            scales: [N,3] float linear scales (standard deviations), > 0, stage units.
            joint_transforms: [J,4,4] float rigid bone transforms (rest pose -> posed world, as the
                ``bone_transforms`` of ``poses.npz``); required when a skeleton was given, and
                rejected otherwise.
            mesh_points: the points [V,3] (stage units) of every mesh given to the writer, by mesh name;
                required when it was given meshes.
            Numpy arrays, torch tensors (any device) or nested sequences are accepted.

        Raises:
            ValueError: bad shapes or values, a time code that does not increase, a missing or
                unexpected ``joint_transforms`` or mesh, non-rigid bone transforms.
            RuntimeError: the writer is closed.
        """
        if self._closed:
            raise RuntimeError("GaussianUsdWriter is closed")
        if not isinstance(time_code, numbers.Integral) or isinstance(time_code, bool):
            raise TypeError(f"time_code must be an int, got {type(time_code).__name__}")
        time_code = int(time_code)
        if self.time_codes and time_code <= self.time_codes[-1]:
            raise ValueError(f"time_code must increase: got {time_code} after {self.time_codes[-1]}")
        count = self.gaussian_count
        positions = _check_array("positions", positions, (count, 3))
        orientations = _check_array("orientations", orientations, (count, 4))
        scales = _check_array("scales", scales, (count, 3))
        if count and not (scales > 0).all():
            raise ValueError(f"scales must be > 0 (linear scales), got a minimum of {scales.min()}")
        if count and not (np.einsum("ni,ni->n", orientations, orientations) > 0).all():
            raise ValueError("orientations hold zero quaternions")
        local_joints = None
        if self._skeleton is not None:
            if joint_transforms is None:
                raise ValueError("joint_transforms is required: the writer was given a skeleton")
            local_joints = self._local_joint_transforms(joint_transforms)
        elif joint_transforms is not None:
            raise ValueError("joint_transforms given but the writer has no skeleton")
        meshes = self._mesh_values(mesh_points)

        extent = gaussian_extent(positions, orientations, scales)
        first = not self.time_codes
        values = {
            "positions": Vt.Vec3fArray.FromNumpy(positions),
            "orientations": Vt.QuatfArray.FromNumpy(np.ascontiguousarray(orientations[:, [1, 2, 3, 0]])),
            "scales": Vt.Vec3fArray.FromNumpy(scales),
        }
        if self.layout == "points":
            widths = 2.0 * scales.max(axis=1) if count else np.zeros(0, dtype=np.float32)
            values["widths"] = Vt.FloatArray.FromNumpy(widths)
            if count:
                radius = widths[:, None] / 2
                extent = np.stack([np.minimum(extent[0], (positions - radius).min(axis=0)),
                                   np.maximum(extent[1], (positions + radius).max(axis=0))])
        values["extent"] = Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(extent, dtype=np.float32))
        with Sdf.ChangeBlock():
            for name, value in values.items():
                self._set(self._attributes[name], value, time_code, first)
            if local_joints is not None:
                translations, rotations = local_joints
                self._set(self._skeleton_attributes["translations"], Vt.Vec3fArray.FromNumpy(translations),
                          time_code, first)
                self._set(self._skeleton_attributes["rotations"], Vt.QuatfArray.FromNumpy(rotations),
                          time_code, first)
            for attribute, value in meshes:
                self._set(attribute, value, time_code, first)
        self.time_codes.append(time_code)
        self._unsaved_frames += 1
        if self._unsaved_frames >= self.flush_every:
            self._flush()

    def _mesh_values(self, mesh_points) -> list[tuple[Usd.Attribute, object]]:
        """(attribute, value) of every mesh's points and extent this frame, from ``mesh_points`` (checked)."""
        given, expected = dict(mesh_points or {}), set(self._mesh_attributes)
        if set(given) != expected:
            missing, unknown = sorted(expected - set(given)), sorted(set(given) - expected)
            wrong = f"missing {', '.join(missing)}" if missing else f"unknown {', '.join(unknown)}"
            raise ValueError(f"mesh_points must hold the points of every mesh the writer was given "
                             f"({', '.join(self._mesh_attributes) or 'none'}): {wrong}")
        values = []
        for name, (count, points_attribute, extent_attribute) in self._mesh_attributes.items():
            points = _check_array(f"mesh_points[{name!r}]", given[name], (count, 3))
            extent = np.stack([points.min(axis=0), points.max(axis=0)])
            values += [(points_attribute, Vt.Vec3fArray.FromNumpy(points)),
                       (extent_attribute, Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(extent, dtype=np.float32)))]
        return values

    def _local_joint_transforms(self, joint_transforms) -> tuple[np.ndarray, np.ndarray]:
        """Bone transforms [J,4,4] -> per-joint local (translations [J,3], rotations [J,4] x,y,z,w) float32."""
        parents, _, bind = self._skeleton
        return local_joint_transforms(joint_transforms, parents, bind)

    # -- finishing -------------------------------------------------------------------------------

    def _save(self) -> None:
        try:
            self._layer.Save()
        except Tf.ErrorException as error:
            raise _save_error(self.path, error) from None

    def _flush(self) -> None:
        if self.time_codes:
            self._stage.SetStartTimeCode(self.time_codes[0])
            self._stage.SetEndTimeCode(self.time_codes[-1])
        self._save()
        self._unsaved_frames = 0

    def close(self) -> str:
        """Finish the file (time range metadata, final save) and rename it to ``path``.

        Returns:
            the final path.

        Raises:
            ValueError: no frame was written (the temporary file is removed).
            RuntimeError: the writer was aborted or closed already.
            OSError: the final save failed (the temporary file is removed, ``path`` left as it was).
        """
        if self._closed:
            raise RuntimeError("GaussianUsdWriter is closed")
        if not self.time_codes:
            self.abort()
            raise ValueError("no frame was written: nothing to save")
        try:
            self._flush()
        except BaseException:
            self.abort()
            raise
        self._release()
        try:
            os.replace(self.temporary_path, self.path)
        except BaseException:
            self._discard()
            raise
        return self.path

    def abort(self) -> None:
        """Stop without writing ``path``: the temporary file is deleted. Safe to call more than once."""
        if not self._closed:
            self._discard()

    def _release(self) -> None:
        self._closed = True
        self._attributes = {}
        self._skeleton_attributes = {}
        self._mesh_attributes = {}
        self._stage = None
        self._layer = None  # the last reference: the layer leaves Sdf's registry and unmaps the file

    def _discard(self) -> None:
        self._release()
        if os.path.exists(self.temporary_path):
            os.remove(self.temporary_path)

    def __del__(self):
        # Dropped without close(): do not leave the temporary file behind.
        try:
            if not getattr(self, "_closed", True):
                self._discard()
        except Exception:  # pragma: no cover - interpreter shutdown
            pass

    def __enter__(self) -> "GaussianUsdWriter":
        return self

    def __exit__(self, exc_type, exc, traceback) -> bool:
        if exc_type is not None:
            self.abort()
        elif not self._closed:
            self.close()
        return False


def _find_gaussians_prim(stage: Usd.Stage, prim_path: str | None) -> Usd.Prim:
    if prim_path is not None:
        prim = stage.GetPrimAtPath(prim_path)
        if not prim or not (prim.IsA(UsdVol.ParticleField3DGaussianSplat) or prim.IsA(UsdGeom.Points)):
            raise ValueError(f"no ParticleField3DGaussianSplat or Points prim at {prim_path!r}")
        return prim
    for prim in stage.Traverse():
        if prim.IsA(UsdVol.ParticleField3DGaussianSplat):
            return prim
    for prim in stage.Traverse():
        if prim.IsA(UsdGeom.Points) and prim.GetAttribute("primvars:orientations"):
            return prim
    raise ValueError("the stage has no ParticleField3DGaussianSplat prim nor Gaussian Points prim")


def read_gaussian_usd(path: str | os.PathLike, *, prim_path: str | None = None) -> dict:
    """Read back an animation written by :class:`GaussianUsdWriter` (either layout), in our conventions.

    Args:
        path: the ``.usdc``/``.usd``/``.usda`` file.
        prim_path: the Gaussians prim; default: the first ParticleField3DGaussianSplat, else the first
            Points prim with an ``orientations`` primvar.

    Returns:
        dict with ``layout`` (str), ``prim_path`` (str), ``time_codes`` [T] int64 (the union of the time
        samples of positions, orientations and scales), per-frame float32 arrays ``positions`` [T,N,3],
        ``orientations`` [T,N,4] (w, x, y, z), ``scales`` [T,N,3], ``extent`` [T,2,3] (and ``widths`` [T,N]
        for points), the authored-once ``opacities`` [N], ``sh_coeffs`` [N,(d+1)^2,3], ``sh_degree`` (int),
        ``display_color`` [N,3], and stage metadata ``fps`` (timeCodesPerSecond), ``frames_per_second``,
        ``up_axis`` ("Y"/"Z"), ``meters_per_unit``, ``start_time_code``, ``end_time_code``. With a
        UsdSkel rig, also ``joint_names`` (list of str), ``joint_paths`` (list of str) and
        ``joint_transforms`` [T,J,4,4] float64, the skinning transforms that usd-core's UsdSkel computes
        (column convention: the bone transforms given to the writer).

    Raises:
        ValueError: the file cannot be opened as a stage or holds no Gaussians prim.
    """
    path = os.fspath(path)
    cached = Sdf.Layer.Find(path)
    if cached:
        cached.Reload(True)  # a layer still open from before may be stale after a rename
    try:
        stage = Usd.Stage.Open(path)
    except Tf.ErrorException as error:
        raise ValueError(f"{path}: cannot open as a USD stage: {error}") from None
    prim = _find_gaussians_prim(stage, prim_path)
    is_particlefield = prim.IsA(UsdVol.ParticleField3DGaussianSplat)
    if is_particlefield:
        gaussians = UsdVol.ParticleField3DGaussianSplat(prim)
        attributes = {
            "positions": gaussians.GetPositionsAttr(),
            "orientations": gaussians.GetOrientationsAttr(),
            "scales": gaussians.GetScalesAttr(),
            "extent": gaussians.GetExtentAttr(),
        }
        opacities = gaussians.GetOpacitiesAttr().Get()
        sh_degree = gaussians.GetRadianceSphericalHarmonicsDegreeAttr().Get()
        coefficients = gaussians.GetRadianceSphericalHarmonicsCoefficientsAttr().Get()
        display_color = gaussians.GetDisplayColorAttr().Get()
    else:
        points = UsdGeom.Points(prim)
        attributes = {
            "positions": points.GetPointsAttr(),
            "orientations": prim.GetAttribute("primvars:orientations"),
            "scales": prim.GetAttribute("primvars:scales"),
            "widths": points.GetWidthsAttr(),
            "extent": points.GetExtentAttr(),
        }
        opacities = points.GetDisplayOpacityAttr().Get()
        sh_degree = prim.GetAttribute("primvars:sphericalHarmonicsDegree").Get()
        coefficients = prim.GetAttribute("primvars:sphericalHarmonicsCoefficients").Get()
        display_color = points.GetDisplayColorAttr().Get()

    time_codes = sorted({t for name in ("positions", "orientations", "scales")
                         for t in attributes[name].GetTimeSamples()})
    result: dict = {
        "layout": "particlefield" if is_particlefield else "points",
        "prim_path": str(prim.GetPath()),
        "time_codes": np.asarray(time_codes, dtype=np.int64),
    }
    for name, attribute in attributes.items():
        frames = [np.asarray(attribute.Get(Usd.TimeCode(t)), dtype=np.float32) for t in time_codes]
        if name == "orientations":
            frames = [frame.reshape(-1, 4)[:, [3, 0, 1, 2]] for frame in frames]
        width = {"positions": 3, "orientations": 4, "scales": 3, "extent": 3, "widths": None}[name]
        shape = (-1,) if width is None else (-1, width)
        result[name] = np.stack([frame.reshape(shape) for frame in frames]) if frames else np.zeros((0, 0))
    count = result["positions"].shape[1] if time_codes else 0
    sh_degree = int(sh_degree) if sh_degree is not None else 0
    result["sh_degree"] = sh_degree
    result["opacities"] = np.asarray(opacities if opacities is not None else [], dtype=np.float32)
    result["sh_coeffs"] = np.asarray(coefficients if coefficients is not None else [],
                                     dtype=np.float32).reshape(count, (sh_degree + 1) ** 2, 3)
    result["display_color"] = np.asarray(display_color if display_color is not None else [],
                                         dtype=np.float32).reshape(-1, 3)
    result["fps"] = float(stage.GetTimeCodesPerSecond())
    result["frames_per_second"] = float(stage.GetFramesPerSecond())
    result["up_axis"] = str(UsdGeom.GetStageUpAxis(stage))
    result["meters_per_unit"] = float(UsdGeom.GetStageMetersPerUnit(stage))
    result["start_time_code"] = float(stage.GetStartTimeCode())
    result["end_time_code"] = float(stage.GetEndTimeCode())

    skeleton_prim = next((p for p in stage.Traverse() if p.IsA(UsdSkel.Skeleton)), None)
    if skeleton_prim is not None:
        skeleton = UsdSkel.Skeleton(skeleton_prim)
        query = UsdSkel.Cache().GetSkelQuery(skeleton)
        result["joint_paths"] = [str(token) for token in skeleton.GetJointsAttr().Get()]
        names = skeleton.GetJointNamesAttr().Get()
        result["joint_names"] = [str(token) for token in names] if names else list(result["joint_paths"])
        result["joint_transforms"] = np.stack(
            [_from_usd_matrices(query.ComputeSkinningTransforms(Usd.TimeCode(t))) for t in time_codes]
        ) if time_codes else np.zeros((0, len(result["joint_paths"]), 4, 4))
    return result
