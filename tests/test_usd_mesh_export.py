"""The avatar's skinned mesh as OpenUSD (warpavatar.io.usd_mesh): usd-core's own UsdSkel poses it as the project's
skinning does, at the motion's time codes, and OpenUSD's validators find no error in the files."""

import dataclasses
import os

import numpy as np
import pytest
from pxr import Sdf, Tf, Usd, UsdGeom, UsdShade, UsdSkel, UsdUtils, UsdValidation

from warpavatar.io.usd_mesh import srgb_to_linear, texture_path_for, write_usd_mesh
from warpavatar.mesh import MeshAnimation
from warpavatar.mesh.skin import lbs_vertices

POSE_TOLERANCE = 1e-4  # [m]


# ---------------------------------------------------------------------------------------------------- helpers
def skinned_points(path, time_codes) -> tuple[list[str], np.ndarray]:
    """(the skinned mesh's prim paths, its points [T,V,3] as usd-core's UsdSkel skins them at ``time_codes``)."""
    stage = Usd.Stage.Open(os.fspath(path))
    cache = UsdSkel.Cache()
    root = UsdSkel.Root(stage.GetDefaultPrim())
    assert root, "the default prim is a SkelRoot"
    cache.Populate(root, Usd.PrimDefaultPredicate)
    bindings = cache.ComputeSkelBindings(root, Usd.PrimDefaultPredicate)
    assert len(bindings) == 1 and len(bindings[0].GetSkinningTargets()) == 1
    skeleton_query = cache.GetSkelQuery(bindings[0].GetSkeleton())
    target = bindings[0].GetSkinningTargets()[0]
    points_attribute = UsdGeom.Mesh(target.GetPrim()).GetPointsAttr()
    frames = []
    for code in time_codes:
        time = code if isinstance(code, Usd.TimeCode) else Usd.TimeCode(float(code))
        points = points_attribute.Get(time)
        assert target.ComputeSkinnedPoints(skeleton_query.ComputeSkinningTransforms(time), points, time)
        frames.append(np.asarray(points, dtype=np.float64))
    return [str(target.GetPrim().GetPath())], np.stack(frames)


def validation_errors(path) -> list[str]:
    """Errors of every validator OpenUSD registers (the UsdValidation framework, as usdchecker runs it)."""
    registry = UsdValidation.ValidationRegistry()
    context = UsdValidation.ValidationContext(registry.GetOrLoadAllValidators())
    stage = Usd.Stage.Open(os.fspath(path))
    return [f"{error.GetName()}: {error.GetMessage()}" for error in context.Validate(stage)
            if error.GetType() == UsdValidation.ValidationErrorType.Error]


# ------------------------------------------------------------------------------------------------------ tests
@pytest.mark.parametrize("suffix", [".usdc", ".usdz"])
def test_usd_skel_poses_the_mesh_as_the_project_does(tmp_path, swaying_body, suffix):
    mesh, animation = swaying_body
    written = write_usd_mesh(tmp_path / f"avatar{suffix}", mesh, animation)
    expected_codes = animation.frame_ids - animation.frame_ids[0]
    np.testing.assert_array_equal(written.time_codes, expected_codes)
    assert written.vertex_cache and written.frame_count == animation.frame_count
    _, posed = skinned_points(written.path, written.time_codes)
    reference = np.stack([lbs_vertices(mesh, animation.joint_transforms[t], animation.vertex_offsets[t])
                          for t in range(animation.frame_count)])
    np.testing.assert_allclose(posed, reference, atol=POSE_TOLERANCE)
    # the offsets matter: skinning alone would miss them
    assert np.abs(posed - np.stack([lbs_vertices(mesh, transforms) for transforms in animation.joint_transforms])
                  ).max() > 10 * POSE_TOLERANCE
    stage = Usd.Stage.Open(os.fspath(written.path))
    assert stage.GetTimeCodesPerSecond() == stage.GetFramesPerSecond() == animation.fps
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (0.0, float(expected_codes[-1]))
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z and UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    motion = UsdSkel.Animation(stage.GetPrimAtPath("/Avatar/Animation"))
    assert list(motion.GetRotationsAttr().GetTimeSamples()) == expected_codes.tolist()


def test_stage_layout(tmp_path, swaying_body):
    mesh, animation = swaying_body
    written = write_usd_mesh(tmp_path / "avatar.usd", mesh, animation)
    assert written.texture_path == tmp_path / "avatar.texture.png" == texture_path_for(written.path)
    assert sorted(os.listdir(tmp_path)) == ["avatar.texture.png", "avatar.usd"]
    assert written.path.read_bytes()[:8] == b"PXR-USDC"  # the binary crate format
    stage = Usd.Stage.Open(os.fspath(written.path))
    assert stage.GetDefaultPrim().GetPath() == "/Avatar" and stage.GetDefaultPrim().GetTypeName() == "SkelRoot"
    skeleton = UsdSkel.Skeleton(stage.GetPrimAtPath("/Avatar/Skeleton"))
    assert list(skeleton.GetJointNamesAttr().Get()) == mesh.joint_names
    joints = [str(path) for path in skeleton.GetJointsAttr().Get()]
    assert [path.rpartition("/")[2] for path in joints] == [Tf.MakeValidIdentifier(n) for n in mesh.joint_names]
    bind = np.swapaxes(np.asarray(skeleton.GetBindTransformsAttr().Get()), 1, 2)
    np.testing.assert_allclose(bind[:, :3, 3], mesh.joint_heads, atol=1e-6)
    np.testing.assert_allclose(bind[:, :3, :3], np.broadcast_to(np.eye(3), (len(joints), 3, 3)))
    # UsdSkel gives the skinning transforms back (rest pose -> posed world)
    query = UsdSkel.Cache().GetSkelQuery(skeleton)
    for t, code in enumerate(written.time_codes):
        transforms = np.swapaxes(np.asarray(query.ComputeSkinningTransforms(Usd.TimeCode(float(code)))), 1, 2)
        np.testing.assert_allclose(transforms, animation.joint_transforms[t], atol=2e-5)

    body = UsdGeom.Mesh(stage.GetPrimAtPath("/Avatar/Body"))
    np.testing.assert_array_equal(np.asarray(body.GetPointsAttr().Get()), mesh.vertices)  # default: the rest mesh
    assert body.GetPointsAttr().GetNumTimeSamples() == animation.frame_count
    np.testing.assert_array_equal(np.asarray(body.GetFaceVertexIndicesAttr().Get()), mesh.faces.reshape(-1))
    assert set(body.GetFaceVertexCountsAttr().Get()) == {3}
    assert body.GetOrientationAttr().Get() == UsdGeom.Tokens.rightHanded
    primvars = UsdGeom.PrimvarsAPI(body.GetPrim())
    st = primvars.GetPrimvar("st")
    assert st.GetTypeName() == Sdf.ValueTypeNames.TexCoord2fArray and st.GetInterpolation() == "vertex"
    np.testing.assert_allclose(np.asarray(st.Get()), np.stack([mesh.uvs[:, 0], 1 - mesh.uvs[:, 1]], 1), atol=1e-7)
    np.testing.assert_allclose(np.asarray(body.GetDisplayColorAttr().Get()), srgb_to_linear(mesh.vertex_colors))
    binding = UsdSkel.BindingAPI(body.GetPrim())
    indices, weights = binding.GetJointIndicesPrimvar(), binding.GetJointWeightsPrimvar()
    assert indices.GetElementSize() == weights.GetElementSize() == 4
    assert indices.GetInterpolation() == weights.GetInterpolation() == "vertex"
    np.testing.assert_array_equal(np.asarray(indices.Get()).reshape(-1, 4), mesh.joint_indices)
    np.testing.assert_array_equal(np.asarray(binding.GetGeomBindTransformAttr().Get()), np.eye(4))
    assert binding.GetSkeletonRel().GetTargets() == [skeleton.GetPath()]

    material, _ = UsdShade.MaterialBindingAPI(body.GetPrim()).ComputeBoundMaterial()
    surface = material.ComputeSurfaceSource()[0]
    assert surface.GetIdAttr().Get() == "UsdPreviewSurface"
    texture = surface.GetInput("diffuseColor").GetConnectedSources()[0][0].source
    texture = UsdShade.Shader(texture.GetPrim())
    assert texture.GetIdAttr().Get() == "UsdUVTexture"
    assert texture.GetInput("sourceColorSpace").Get() == "sRGB"
    assert texture.GetInput("file").Get().resolvedPath == os.fspath(written.texture_path)


def test_validators_report_no_errors(tmp_path, swaying_body):
    mesh, animation = swaying_body
    for suffix in (".usdc", ".usdz"):
        written = write_usd_mesh(tmp_path / f"avatar{suffix}", mesh, animation)
        assert validation_errors(written.path) == [], suffix
        if hasattr(UsdUtils, "ComplianceChecker"):  # the older checker, gone from usd-core 26
            checker = UsdUtils.ComplianceChecker()
            checker.CheckCompliance(os.fspath(written.path))
            assert checker.GetErrors() == [] and checker.GetFailedChecks() == [], suffix
    # the validators do see broken skinning: a mesh bound to a skeleton without the binding schema
    broken = Usd.Stage.Open(os.fspath(tmp_path / "avatar.usdc"))
    broken.GetPrimAtPath("/Avatar/Body").RemoveAPI(UsdSkel.BindingAPI)
    broken.Export(os.fspath(tmp_path / "broken.usda"))
    assert any(error.startswith("MissingSkelBindingAPI:") for error in validation_errors(tmp_path / "broken.usda"))
    # the package holds the layer and its texture: it opens anywhere, alone
    os.rename(tmp_path / "avatar.usdz", tmp_path / "moved.usdz")
    os.remove(tmp_path / "avatar.texture.png")
    stage = Usd.Stage.Open(os.fspath(tmp_path / "moved.usdz"))
    file = UsdShade.Shader(stage.GetPrimAtPath("/Avatar/Materials/Skin/Texture")).GetInput("file").Get()
    assert file.resolvedPath.endswith("moved.usdz[avatar.texture.png]")


def test_rest_pose_static_and_unskinned_meshes(tmp_path, skinned_body):
    written = write_usd_mesh(tmp_path / "rest.usda", skinned_body)
    assert written.frame_count == 0 and not written.vertex_cache
    _, posed = skinned_points(written.path, [Usd.TimeCode.Default()])
    np.testing.assert_allclose(posed[0], skinned_body.vertices, atol=1e-6)  # no animation: the rest pose
    assert validation_errors(written.path) == []
    plain = dataclasses.replace(skinned_body, joint_indices=None, joint_weights=None, texture=None, uvs=None,
                                up=np.array([0.0, 1.0, 0.0], np.float32))
    written = write_usd_mesh(tmp_path / "plain.usdc", plain)
    assert written.texture_path is None
    assert sorted(os.listdir(tmp_path)) == ["plain.usdc", "rest.texture.png", "rest.usda"]
    stage = Usd.Stage.Open(os.fspath(written.path))
    assert stage.GetDefaultPrim().GetTypeName() == "Xform" and UsdGeom.GetStageUpAxis(stage) == "Y"
    reader = UsdShade.Shader(stage.GetPrimAtPath("/Avatar/Materials/Skin/ColorReader"))
    assert reader.GetInput("varname").Get() == "displayColor"
    assert validation_errors(written.path) == []
    # an up that is neither +Z nor +Y: a Z-up stage whose root turns the avatar's up to +Z
    tilted = dataclasses.replace(skinned_body, up=np.array([1.0, 0.0, 1.0], np.float32))
    written = write_usd_mesh(tmp_path / "tilted.usda", tilted)
    stage = Usd.Stage.Open(os.fspath(written.path))
    to_world = np.asarray(UsdGeom.Xformable(stage.GetDefaultPrim()).ComputeLocalToWorldTransform(0)).T
    assert UsdGeom.GetStageUpAxis(stage) == "Z"
    np.testing.assert_allclose(to_world[:3, :3] @ np.array([1.0, 0.0, 1.0]) / np.sqrt(2), [0, 0, 1], atol=1e-7)
    assert validation_errors(written.path) == []


def test_grown_joints_are_joints_of_the_skeleton(tmp_path, skinned_body, export_motion):
    names = list(skinned_body.joint_names)
    grown_parents = [names.index("Hips"), names.index("LowerArmL")]
    parents = np.concatenate([skinned_body.joint_parents, grown_parents]).astype(np.int32)
    heads = np.concatenate([skinned_body.joint_heads, skinned_body.joint_heads[parents[-2:]] + 0.05]).astype(np.float32)
    mesh = dataclasses.replace(skinned_body, joint_names=names + ["Hips grown", "LowerArmL grown"],
                               joint_parents=parents, joint_heads=heads,
                               joint_indices=np.where(skinned_body.joint_indices == 3, len(names),
                                                      skinned_body.joint_indices).astype(np.int32))
    rng = np.random.default_rng(4)
    base = np.asarray(export_motion.bone_transforms, dtype=np.float64)
    grown = base[:, parents[-2:]].copy()
    angle = rng.uniform(-0.5, 0.5, size=(len(base), 2))
    turn = np.zeros((len(base), 2, 4, 4))
    turn[..., 0, 0] = turn[..., 1, 1] = np.cos(angle)
    turn[..., 0, 1], turn[..., 1, 0] = -np.sin(angle), np.sin(angle)
    turn[..., 2, 2] = turn[..., 3, 3] = 1.0
    pivot = np.eye(4)[None, None].repeat(len(base), 0).repeat(2, 1)
    pivot[..., :3, 3] = heads[-2:]
    grown = grown @ pivot @ turn @ np.linalg.inv(pivot)
    animation = MeshAnimation(joint_transforms=np.concatenate([base, grown], 1).astype(np.float32),
                              frame_ids=export_motion.frame_ids, fps=export_motion.fps)
    written = write_usd_mesh(tmp_path / "grown.usdc", mesh, animation)
    assert not written.vertex_cache
    _, posed = skinned_points(written.path, written.time_codes)
    reference = np.stack([lbs_vertices(mesh, transforms) for transforms in animation.joint_transforms])
    np.testing.assert_allclose(posed, reference, atol=POSE_TOLERANCE)
    stage = Usd.Stage.Open(os.fspath(written.path))
    joints = [str(path) for path in UsdSkel.Skeleton(stage.GetPrimAtPath("/Avatar/Skeleton")).GetJointsAttr().Get()]
    assert joints[-1].endswith("/LowerArmL/LowerArmL_grown") and joints[-2].endswith("/Hips/Hips_grown")


def test_bad_input_and_atomic_writes(tmp_path, monkeypatch, swaying_body):
    mesh, animation = swaying_body
    with pytest.raises(ValueError, match=r"must end in one of \.usd, \.usdc, \.usda, \.usdz"):
        write_usd_mesh(tmp_path / "avatar.fbx", mesh, animation)
    with pytest.raises(ValueError, match="an animation needs a skinned mesh"):
        write_usd_mesh(tmp_path / "avatar.usdc", dataclasses.replace(mesh, joint_indices=None), animation)
    with pytest.raises(ValueError, match="vertex offsets must have shape"):
        write_usd_mesh(tmp_path / "avatar.usdc", mesh,
                       dataclasses.replace(animation, vertex_offsets=animation.vertex_offsets[:, :5]))
    children_first = np.where(np.arange(len(mesh.joint_names)) == 0, 1, -1).astype(np.int32)
    with pytest.raises(ValueError, match="parent"):
        write_usd_mesh(tmp_path / "avatar.usdc", dataclasses.replace(mesh, joint_parents=children_first))
    assert os.listdir(tmp_path) == []
    # a write that fails keeps the earlier file and leaves no temporary name behind
    for suffix in (".usdz", ".usdc"):
        first = write_usd_mesh(tmp_path / f"avatar{suffix}", mesh, animation)
        before = first.path.read_bytes()
        with monkeypatch.context() as patch:
            patch.setattr(UsdUtils, "CreateNewUsdzPackage", lambda *args: False)
            patch.setattr(Sdf.Layer, "Export", lambda *args, **kwargs: False)
            with pytest.raises(OSError, match=f"avatar\\{suffix}: USD cannot write"):
                write_usd_mesh(tmp_path / f"avatar{suffix}", mesh, animation)
        assert first.path.read_bytes() == before
    assert sorted(os.listdir(tmp_path)) == ["avatar.texture.png", "avatar.usdc", "avatar.usdz"]
