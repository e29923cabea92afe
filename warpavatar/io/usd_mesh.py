"""The avatar's skinned, textured mesh and its motion as OpenUSD (``.usd`` / ``.usdc`` crate, ``.usda`` text, or a
self-contained ``.usdz`` package), through UsdSkel.

The stage (``/Avatar`` is its default prim, a ``SkelRoot`` of kind ``component``):

* ``/Avatar/Skeleton`` (``Skeleton``): the rig's joint paths (``hips/spine/chest``, names made valid
  identifiers, unique among siblings), ``jointNames`` (the names as given), ``bindTransforms`` (each joint's
  world rest frame: unrotated, at its head) and ``restTransforms`` (the same frames, local to the parent);
* ``/Avatar/Animation`` (``SkelAnimation``, the skeleton's ``skel:animationSource``), with a motion: per-joint
  local ``translations`` / ``rotations`` / ``scales`` (ones) time-sampled at the motion's time codes
  (:func:`~warpavatar.io.animation.motion_time_codes`: frame id less the first), with the stage's
  ``timeCodesPerSecond`` and ``framesPerSecond`` the motion's fps and its start and end time codes set. UsdSkel
  then gives back the animation's skinning transforms exactly (rest pose -> posed world);
* ``/Avatar/Body`` (``Mesh``): ``points``, ``faceVertexCounts`` / ``faceVertexIndices`` (counter-clockwise
  seen from outside: USD's default right-handed orientation), vertex ``normals``, ``primvars:st`` (texCoord2f,
  with USD's v up: ``v_usd = 1 - v`` of the mesh's glTF-convention uvs), ``primvars:displayColor`` (the vertex
  colours, sRGB bytes decoded to linear values), ``extent``; bound to the skeleton (``UsdSkel.BindingAPI``:
  ``skel:skeleton``, ``primvars:skel:jointIndices`` / ``jointWeights`` with elementSize 4 and vertex
  interpolation, ``skel:geomBindTransform`` identity) and to the material. Where the animation has vertex
  offsets (cloth and secondary motion that skinning cannot make), ``points`` is time-sampled too: rest + offset
  at each time code, which UsdSkel skins (its points are read at the time being skinned); the normals stay
  those of the rest mesh;
* ``/Avatar/Materials/Skin`` (``UsdPreviewSurface``, roughness 1, metallic 0): its ``diffuseColor`` reads the
  texture atlas (``UsdUVTexture`` of sRGB source, clamped, at ``st``), or without a texture the vertex colours
  (``displayColor``), or a grey.

The texture is a PNG: beside a ``.usd`` / ``.usdc`` / ``.usda`` file as ``NAME.texture.png`` (``NAME``: the
file's name without its suffix), referenced by a relative path; inside a ``.usdz``, which packages the crate
layer and the PNG into one file (``UsdUtils.CreateNewUsdzPackage``). Axes: the stage's ``upAxis`` is the
skeleton's up (``Z`` for ``+Z``, the supplied data, ``Y`` for ``+Y``; another up gets ``Z`` and a rotation on
``/Avatar`` taking it there); ``metersPerUnit`` is 1. Every file is written under a temporary name and renamed
once complete (:mod:`warpavatar.io.output_files`). Matrices are column-vector 4x4 here (USD's row-vector
matrices are their transposes).
"""

from __future__ import annotations

import math
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pxr import Gf, Kind, Sdf, Tf, Usd, UsdGeom, UsdShade, UsdSkel, UsdUtils, Vt

from warpavatar.io.animation import motion_time_codes
from warpavatar.io.gltf import check_mesh
from warpavatar.io.images import write_image
from warpavatar.io.output_files import atomic_path, temporary_path
from warpavatar.io.usd import (_joint_paths, _save_error, _skeleton_fields, _to_usd_matrices, _translation_matrices,
                               local_joint_transforms)
from warpavatar.mesh.mesh_data import AvatarMesh, MeshAnimation

__all__ = ["MESH_SUFFIXES", "UsdMeshFile", "write_usd_mesh", "texture_path_for", "srgb_to_linear"]

MESH_SUFFIXES = (".usd", ".usdc", ".usda", ".usdz")
"""File name endings :func:`write_usd_mesh` writes."""

_ROOT = "/Avatar"
_GREY = (0.5, 0.5, 0.5)


@dataclass(frozen=True)
class UsdMeshFile:
    """What :func:`write_usd_mesh` wrote.

    Attributes:
        path: the USD file.
        texture_path: the PNG written beside it (``.usd`` / ``.usdc`` / ``.usda`` with a texture), else None.
        byte_count: the USD file's size [bytes].
        frame_count: time samples of the animation (0 without one).
        time_codes: [T] int64 time codes of the samples (empty without an animation).
        vertex_cache: whether ``points`` is time-sampled (the animation has vertex offsets).
    """

    path: Path
    texture_path: Path | None
    byte_count: int
    frame_count: int
    time_codes: np.ndarray
    vertex_cache: bool


def texture_path_for(path: str | os.PathLike) -> Path:
    """The texture PNG written beside a ``.usd`` / ``.usdc`` / ``.usda`` file: ``NAME.texture.png``."""
    path = Path(path)
    return path.with_name(f"{path.stem}.texture.png")


def srgb_to_linear(colors: np.ndarray) -> np.ndarray:
    """sRGB-encoded bytes [...,3] uint8 -> linear values in 0..1 (float32), the IEC 61966-2-1 curve."""
    c = np.asarray(colors, dtype=np.float64) / 255.0
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4).astype(np.float32)


def _up_axis(up: np.ndarray) -> tuple[str, np.ndarray | None]:
    """(stage upAxis, None or a [3,3] rotation taking ``up`` to +Z for the root prim)."""
    up = np.asarray(up, dtype=np.float64).reshape(3)
    length = float(np.linalg.norm(up))
    if not math.isfinite(length) or length == 0.0:
        raise ValueError(f"the mesh's up direction must be a non-zero vector, got {up.tolist()}")
    up = up / length
    if up[2] > 1.0 - 1e-6:
        return "Z", None
    if up[1] > 1.0 - 1e-6:
        return "Y", None
    target = np.array([0.0, 0.0, 1.0])
    axis = np.cross(up, target)
    sine, cosine = float(np.linalg.norm(axis)), float(up @ target)
    if sine < 1e-12:  # -Z: half a turn about X
        return "Z", np.diag([1.0, -1.0, -1.0])
    k = axis / sine
    cross = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return "Z", np.eye(3) + sine * cross + (1.0 - cosine) * (cross @ cross)


def _continuous_quaternions(rotations: np.ndarray) -> np.ndarray:
    """[T,J,4] quaternions, each in the hemisphere of the frame before (interpolation goes the short way)."""
    rotations = rotations.copy()
    for t in range(1, rotations.shape[0]):
        flip = (rotations[t] * rotations[t - 1]).sum(-1) < 0
        rotations[t, flip] *= -1.0
    return rotations


def _author_skeleton(stage: Usd.Stage, root: Sdf.Path, mesh: AvatarMesh, animation: MeshAnimation | None,
                     time_codes: np.ndarray) -> UsdSkel.Skeleton:
    names, parents, heads = _skeleton_fields({"names": list(mesh.joint_names), "parents": mesh.joint_parents,
                                              "heads": mesh.joint_heads})
    joints = Vt.TokenArray(_joint_paths(names, parents))
    skeleton = UsdSkel.Skeleton.Define(stage, root.AppendChild("Skeleton"))
    bind = _translation_matrices(heads)
    parent_heads = np.where(parents[:, None] >= 0, heads[np.maximum(parents, 0)], 0.0)
    skeleton.CreateJointsAttr(joints)
    skeleton.CreateJointNamesAttr(Vt.TokenArray(names))
    skeleton.CreateBindTransformsAttr(_to_usd_matrices(bind))
    skeleton.CreateRestTransformsAttr(_to_usd_matrices(_translation_matrices(heads - parent_heads)))
    if animation is None:
        return skeleton
    motion = UsdSkel.Animation.Define(stage, root.AppendChild("Animation"))
    motion.CreateJointsAttr(joints)
    locals_ = [local_joint_transforms(frame, parents, bind) for frame in np.asarray(animation.joint_transforms)]
    translations = np.stack([translation for translation, _ in locals_])
    rotations = _continuous_quaternions(np.stack([rotation for _, rotation in locals_]))
    translations_attr = motion.CreateTranslationsAttr()
    rotations_attr = motion.CreateRotationsAttr()
    scales = Vt.Vec3hArray.FromNumpy(np.ones((len(names), 3), dtype=np.float16))
    scales_attr = motion.CreateScalesAttr(scales)
    with Sdf.ChangeBlock():
        for t, code in enumerate(time_codes.tolist()):
            time = Usd.TimeCode(code)
            translations_attr.Set(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(translations[t])), time)
            rotations_attr.Set(Vt.QuatfArray.FromNumpy(np.ascontiguousarray(rotations[t], dtype=np.float32)), time)
            scales_attr.Set(scales, time)
        # defaults (no time) = the first frame, for readers that open the stage without a time
        translations_attr.Set(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(translations[0])))
        rotations_attr.Set(Vt.QuatfArray.FromNumpy(np.ascontiguousarray(rotations[0], dtype=np.float32)))
    UsdSkel.BindingAPI.Apply(skeleton.GetPrim()).CreateAnimationSourceRel().SetTargets([motion.GetPath()])
    return skeleton


def _extent(points: np.ndarray) -> Vt.Vec3fArray:
    return Vt.Vec3fArray.FromNumpy(np.stack([points.min(0), points.max(0)]).astype(np.float32))


def _author_mesh(stage: Usd.Stage, root: Sdf.Path, mesh: AvatarMesh, animation: MeshAnimation | None,
                 time_codes: np.ndarray, skeleton: UsdSkel.Skeleton | None) -> UsdGeom.Mesh:
    body = UsdGeom.Mesh.Define(stage, root.AppendChild("Body"))
    vertices = np.ascontiguousarray(mesh.vertices, dtype=np.float32)
    faces = np.ascontiguousarray(mesh.faces, dtype=np.int32)
    points = body.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(vertices))
    extent = body.CreateExtentAttr(_extent(vertices))
    body.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(faces.shape[0], 3, dtype=np.int32)))
    body.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(faces.reshape(-1)))
    body.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    body.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
    if mesh.normals is not None:
        normals = np.asarray(mesh.normals, dtype=np.float64)
        normals = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
        body.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(normals.astype(np.float32)))
        body.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
    primvars = UsdGeom.PrimvarsAPI(body.GetPrim())
    if mesh.uvs is not None:
        uvs = np.asarray(mesh.uvs, dtype=np.float32).copy()
        uvs[:, 1] = 1.0 - uvs[:, 1]
        primvars.CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex).Set(
            Vt.Vec2fArray.FromNumpy(uvs))
    if mesh.vertex_colors is not None:
        body.CreateDisplayColorPrimvar(UsdGeom.Tokens.vertex).Set(
            Vt.Vec3fArray.FromNumpy(srgb_to_linear(mesh.vertex_colors)))
    if animation is not None and animation.vertex_offsets is not None:
        offsets = np.asarray(animation.vertex_offsets, dtype=np.float32)
        with Sdf.ChangeBlock():
            for t, code in enumerate(time_codes.tolist()):
                moved = vertices + offsets[t]
                points.Set(Vt.Vec3fArray.FromNumpy(moved), Usd.TimeCode(code))
                extent.Set(_extent(moved), Usd.TimeCode(code))
    if skeleton is not None:
        binding = UsdSkel.BindingAPI.Apply(body.GetPrim())
        binding.CreateSkeletonRel().SetTargets([skeleton.GetPath()])
        binding.CreateJointIndicesPrimvar(False, 4).Set(
            Vt.IntArray.FromNumpy(np.ascontiguousarray(mesh.joint_indices, dtype=np.int32).reshape(-1)))
        binding.CreateJointWeightsPrimvar(False, 4).Set(
            Vt.FloatArray.FromNumpy(np.ascontiguousarray(mesh.joint_weights, dtype=np.float32).reshape(-1)))
        binding.CreateGeomBindTransformAttr(Gf.Matrix4d(1.0))
    return body


def _author_material(stage: Usd.Stage, root: Sdf.Path, mesh: AvatarMesh, body: UsdGeom.Mesh,
                     texture_name: str | None) -> None:
    scope = UsdGeom.Scope.Define(stage, root.AppendChild("Materials"))
    material = UsdShade.Material.Define(stage, scope.GetPath().AppendChild("Skin"))
    surface = UsdShade.Shader.Define(stage, material.GetPath().AppendChild("PreviewSurface"))
    surface.CreateIdAttr("UsdPreviewSurface")
    surface.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(1.0)
    surface.CreateInput("metallic", Sdf.ValueTypeNames.Float).Set(0.0)
    diffuse = surface.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f)
    material.CreateSurfaceOutput().ConnectToSource(surface.ConnectableAPI(), "surface")
    if texture_name is not None:
        reader = UsdShade.Shader.Define(stage, material.GetPath().AppendChild("TexCoordReader"))
        reader.CreateIdAttr("UsdPrimvarReader_float2")
        reader.CreateInput("varname", Sdf.ValueTypeNames.String).Set("st")
        texture = UsdShade.Shader.Define(stage, material.GetPath().AppendChild("Texture"))
        texture.CreateIdAttr("UsdUVTexture")
        texture.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(Sdf.AssetPath(f"./{texture_name}"))
        texture.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set("sRGB")
        texture.CreateInput("wrapS", Sdf.ValueTypeNames.Token).Set("clamp")
        texture.CreateInput("wrapT", Sdf.ValueTypeNames.Token).Set("clamp")
        texture.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(
            reader.ConnectableAPI(), "result")
        diffuse.ConnectToSource(texture.ConnectableAPI(), "rgb")
        texture.CreateOutput("rgb", Sdf.ValueTypeNames.Float3)
        reader.CreateOutput("result", Sdf.ValueTypeNames.Float2)
    elif mesh.vertex_colors is not None:
        reader = UsdShade.Shader.Define(stage, material.GetPath().AppendChild("ColorReader"))
        reader.CreateIdAttr("UsdPrimvarReader_float3")
        reader.CreateInput("varname", Sdf.ValueTypeNames.String).Set("displayColor")
        reader.CreateOutput("result", Sdf.ValueTypeNames.Float3)
        diffuse.ConnectToSource(reader.ConnectableAPI(), "result")
    else:
        diffuse.Set(Gf.Vec3f(*_GREY))
    UsdShade.MaterialBindingAPI.Apply(body.GetPrim()).Bind(material)


def _build_stage(mesh: AvatarMesh, animation: MeshAnimation | None, texture_name: str | None
                 ) -> tuple[Usd.Stage, np.ndarray]:
    stage = Usd.Stage.CreateInMemory("avatar.usda")
    up_axis, rotation = _up_axis(mesh.up)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z if up_axis == "Z" else UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.GetRootLayer().customLayerData = {"creator": "warpavatar"}
    root_path = Sdf.Path(_ROOT)
    skinned = mesh.joint_indices is not None
    root = (UsdSkel.Root.Define(stage, root_path) if skinned else UsdGeom.Xform.Define(stage, root_path))
    Usd.ModelAPI(root.GetPrim()).SetKind(Kind.Tokens.component)
    stage.SetDefaultPrim(root.GetPrim())
    if rotation is not None:
        matrix = np.eye(4)
        matrix[:3, :3] = rotation
        UsdGeom.Xformable(root.GetPrim()).AddTransformOp().Set(Gf.Matrix4d(matrix.T.tolist()))
    time_codes = np.zeros(0, dtype=np.int64)
    if animation is not None:
        time_codes = motion_time_codes(animation.frame_ids)
        fps = float(animation.fps)
        stage.SetTimeCodesPerSecond(fps)
        stage.SetFramesPerSecond(fps)
        stage.SetStartTimeCode(float(time_codes[0]))
        stage.SetEndTimeCode(float(time_codes[-1]))
    skeleton = _author_skeleton(stage, root_path, mesh, animation, time_codes) if skinned else None
    body = _author_mesh(stage, root_path, mesh, animation, time_codes, skeleton)
    _author_material(stage, root_path, mesh, body, texture_name)
    return stage, time_codes


def _export(layer: Sdf.Layer, destination: Path, final: Path, file_format: str) -> None:
    try:
        ok = layer.Export(os.fspath(destination), args={"format": file_format})
    except Tf.ErrorException as error:
        raise _save_error(os.fspath(final), error) from None
    if not ok:
        raise OSError(f"{final}: USD cannot write the file")


def write_usd_mesh(path: str | os.PathLike, mesh: AvatarMesh, animation: MeshAnimation | None = None
                   ) -> UsdMeshFile:
    """Write a mesh, and optionally its animation, as an OpenUSD stage with UsdSkel (see the module docstring).

    Args:
        path: the output file: ``.usd`` or ``.usdc`` (binary crate), ``.usda`` (text) or ``.usdz`` (a package
            holding the crate layer and its texture).
        mesh: the canonical mesh; skinned (:func:`warpavatar.mesh.skin.skin_mesh`) for a rig and an animation.
        animation: the motion (:func:`warpavatar.mesh.skin.mesh_animation`), or None for the rest pose.

    Returns:
        a :class:`UsdMeshFile` saying what was written.

    Raises:
        ValueError: a suffix other than :data:`MESH_SUFFIXES`, or a malformed mesh or animation (one line naming
            the field; an animation needs a skinned mesh, a rig with every parent before its children).
        OSError: a file cannot be written (:class:`~warpavatar.io.output_files.DiskFullError` for a full disk);
            nothing is left under a temporary name, and the earlier file at ``path`` is kept.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise ValueError(f"{path}: a USD mesh file must end in one of {', '.join(MESH_SUFFIXES)}")
    check_mesh(mesh, animation)
    if animation is not None and animation.vertex_offsets is not None \
            and not np.isfinite(np.asarray(animation.vertex_offsets)).all():
        raise ValueError("the animation's vertex offsets are not all finite")
    has_texture = mesh.texture is not None and mesh.uvs is not None
    texture_name = f"{path.stem}.texture.png" if has_texture else None
    stage, time_codes = _build_stage(mesh, animation, texture_name)
    layer = stage.GetRootLayer()
    path.parent.mkdir(parents=True, exist_ok=True)
    texture_file = None
    if suffix == ".usdz":
        staging = temporary_path(path)
        staging.mkdir()
        try:
            layer_file = staging / f"{path.stem}.usdc"
            _export(layer, layer_file, path, "usdc")
            if has_texture:
                write_image(staging / texture_name, np.asarray(mesh.texture, dtype=np.uint8), fsync=False)
            with atomic_path(path, suffix=".usdz") as temporary:
                try:
                    ok = UsdUtils.CreateNewUsdzPackage(Sdf.AssetPath(os.fspath(layer_file)), os.fspath(temporary))
                except Tf.ErrorException as error:
                    raise _save_error(os.fspath(path), error) from None
                if not ok:
                    raise OSError(f"{path}: USD cannot write the package")
        finally:
            shutil.rmtree(staging, ignore_errors=True)
    else:
        with atomic_path(path, suffix=suffix) as temporary:
            _export(layer, temporary, path, "usda" if suffix == ".usda" else "usdc")
            if has_texture:
                texture_file = texture_path_for(path)
                write_image(texture_file, np.asarray(mesh.texture, dtype=np.uint8))
    frame_count = 0 if animation is None else animation.frame_count
    vertex_cache = animation is not None and animation.vertex_offsets is not None
    return UsdMeshFile(path=path, texture_path=texture_file, byte_count=path.stat().st_size, frame_count=frame_count,
                       time_codes=time_codes, vertex_cache=vertex_cache)
