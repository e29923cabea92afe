"""The files warpavatar writes, read by clients that are not warpavatar: OpenUSD's own validators (every kind of
USD the exporters write), the stage timing a DCC tool plays the animation by, and the 3DGS ``.ply`` read by
``plyfile``, an independent PLY parser.

How Blender reads the timing (its USD importer, checked in 4.5 and 5.0): it sets the scene's frame range from
``startTimeCode`` / ``endTimeCode`` and shows time code ``t`` at scene frame ``t``, one to one, but leaves the
scene's frame rate as it was (24 by default), whatever ``framesPerSecond`` says. So the file must count its time
codes in frames of the motion's clock and declare that clock in both ``timeCodesPerSecond`` and
``framesPerSecond``; ``tools/render_usd_blender.py`` then sets the scene's rate from ``framesPerSecond``.
"""

import numpy as np
import pytest
import torch

pytest.importorskip("pxr")  # usd-core is a dependency; skip cleanly where it is absent (the GPU machine)

from pxr import Sdf, Usd, UsdGeom, UsdSkel, UsdValidation

from conftest import small_avatar
from warpavatar import data
from warpavatar.cli import animate
from warpavatar.extensions.joint_growth import ExtraJoints
from warpavatar.fit.outputs import write_canonical_ply
from warpavatar.io.usd import read_gaussian_usd
from warpavatar.model import GaussianModel

MOTION = data.demo_subject_path() / "novel_pose" / "dance_cam000"  # frame ids 0, 3, 6, ... at 30 fps
EXPORTS = {  # name: (animate options, grow a joint first)
    "particlefield": ([], False),
    "points": (["--layout", "points"], False),
    "particlefield_skeleton": (["--skeleton"], False),
    "points_skeleton": (["--layout", "points", "--skeleton"], False),
    "points_skeleton_grown_joint": (["--layout", "points", "--skeleton"], True),
}


@pytest.fixture(scope="module")
def exports(tmp_path_factory):
    """Every kind of USD warpavatar-animate writes, from one small avatar and 4 rows of the demo's dance."""
    folder = tmp_path_factory.mktemp("clients")
    video = data.load_video_folder(data.demo_subject_path() / "train", max_frames=3)
    paths = {}
    for grown in (False, True):
        avatar = small_avatar(video.skeleton, seed=4, per_bone=4, cells=10, distill_steps=20, random_frames=True)
        if grown:  # a joint grown under joint 4 (ToMiE), turned away from its parent so that it animates
            bones = torch.as_tensor(video.bone_transforms, dtype=torch.float32)
            parents = torch.tensor([4])
            extra = ExtraJoints(parents, torch.as_tensor(video.skeleton.heads)[parents], bones,
                                torch.arange(bones.shape[0], dtype=torch.float32) / 30, extent=1.0,
                                hidden_position=8, hidden_rotation=8, layers=1)
            with torch.no_grad():
                extra.rotation_mlp[-1].bias.copy_(torch.tensor([0.0, 0.5, 0.0]))
            avatar.field.add_joints(parents)
            avatar.add_part(extra)
        avatar_dir = folder / ("grown" if grown else "plain")
        avatar_dir.mkdir()
        avatar.save(avatar_dir / "avatar.pt")
        for name, (options, with_grown_joint) in EXPORTS.items():
            if with_grown_joint != grown:
                continue
            paths[name] = folder / f"{name}.usdc"
            assert animate.main([str(avatar_dir), "--motion", str(MOTION), "-o", str(paths[name]), "--frames", "2:6",
                                 "--no-progress", "--device", "cpu", *options]) == 0
    return paths


def _all_validators():
    registry = UsdValidation.ValidationRegistry()
    names = [metadata.name for metadata in registry.GetAllValidatorMetadata()]
    return names, registry.GetOrLoadValidatorsByName(names)


def _validate(stage) -> tuple[list[str], list[str]]:
    """(errors, other findings) of every registered OpenUSD validator on ``stage``, each as one line."""
    _, validators = _all_validators()
    findings = UsdValidation.ValidationContext(validators).Validate(stage)
    lines = {"errors": [], "other": []}
    for finding in findings:
        validator = finding.GetValidator()
        name = validator.GetMetadata().name if validator else "?"
        sites = ", ".join(str(site.GetPrim().GetPath()) for site in finding.GetSites() if site.IsPrim())
        line = f"{finding.GetType()} {name} at [{sites}]: {finding.GetMessage()}"
        lines["errors" if finding.GetType() == UsdValidation.ValidationErrorType.Error else "other"].append(line)
    return lines["errors"], lines["other"]


def test_the_validators_that_run():
    """The validators of usd-core 26.11 cover the schemas the exports use (UsdGeom, UsdSkel, core metadata)."""
    names, validators = _all_validators()
    assert len(validators) == len(names) >= 30
    for expected in ("usdValidation:StageMetadataChecker", "usdValidation:AttributeTypeMismatch",
                     "usdValidation:CompositionErrorTest", "usdGeomValidators:StageMetadataChecker",
                     "usdGeomValidators:EncapsulationChecker", "usdSkelValidators:SkelBindingApiValidator",
                     "usdSkelValidators:SkelBindingApiAppliedValidator", "usdUtilsValidators:FileExtensionValidator"):
        assert expected in names


def test_the_validators_catch_what_they_check(tmp_path):
    """On a stage with the faults they look for, the same validators report errors (so a pass means something)."""
    stage = Usd.Stage.CreateNew(str(tmp_path / "faulty.usda"))  # no upAxis, metersPerUnit or default prim
    UsdGeom.Points.Define(stage, "/Avatar/Gaussians")
    UsdGeom.Points.Define(stage, "/Avatar/Gaussians/Nested")  # a gprim inside a gprim
    mesh = stage.DefinePrim("/Avatar/Body", "Mesh")
    mesh.CreateRelationship(UsdSkel.Tokens.skelSkeleton).SetTargets([Sdf.Path("/Avatar/Rig")])  # no SkelBindingAPI
    errors, _ = _validate(stage)
    text = "\n".join(errors)
    assert "usdGeomValidators:StageMetadataChecker" in text
    assert "usdValidation:StageMetadataChecker" in text
    assert "usdGeomValidators:EncapsulationChecker" in text
    assert "usdSkelValidators:SkelBindingApiAppliedValidator" in text


@pytest.mark.parametrize("name", list(EXPORTS))
def test_every_usd_export_passes_openusd_validation(exports, name):
    stage = Usd.Stage.Open(str(exports[name]))
    errors, other = _validate(stage)  # (none of either today)
    assert not errors, "\n".join([f"{name}: {len(errors)} error(s):", *errors, "warnings and notes:", *other])
    # what was validated is the export: its prims are there
    assert stage.GetPrimAtPath("/Avatar/Gaussians").IsValid()
    assert stage.GetPrimAtPath("/Avatar/Rig").IsValid() == ("skeleton" in name)


@pytest.mark.parametrize("name", list(EXPORTS))
def test_usd_timing_is_what_dcc_tools_play(exports, name):
    """Time codes count frames of the motion's clock (frame ids 6, 9, 12, 15 at 30 fps), declared in both rates."""
    stage = Usd.Stage.Open(str(exports[name]))
    layer = stage.GetRootLayer()
    assert layer.HasTimeCodesPerSecond() and layer.HasFramesPerSecond()
    assert stage.GetTimeCodesPerSecond() == stage.GetFramesPerSecond() == 30.0
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == (0.0, 9.0)
    usd = read_gaussian_usd(exports[name])
    assert list(usd["time_codes"]) == [0, 3, 6, 9]
    gaussians = stage.GetPrimAtPath("/Avatar/Gaussians")
    positions = gaussians.GetAttribute("points" if "points" in name else "positions")
    assert positions.GetTimeSamples() == [0.0, 3.0, 6.0, 9.0]
    # between rows, what a player shows at an integer frame is interpolated linearly by USD
    halfway = np.asarray(positions.Get(Usd.TimeCode(1.5)))
    np.testing.assert_allclose(halfway, 0.5 * (usd["positions"][0] + usd["positions"][1]), atol=1e-6)
    if "skeleton" in name:
        animation = UsdSkel.Animation(stage.GetPrimAtPath("/Avatar/Rig/Animation"))
        assert animation.GetRotationsAttr().GetTimeSamples() == [0.0, 3.0, 6.0, 9.0]


def test_usd_output_frame_rate_option(exports, tmp_path):
    """--fps re-times the output: the same time codes, played at the given rate."""
    output = tmp_path / "slow.usdc"
    avatar_dir = exports["points"].parent / "plain"
    assert animate.main([str(avatar_dir), "--motion", str(MOTION), "-o", str(output), "--frames", "0:3", "--fps", "24",
                         "--no-progress", "--device", "cpu"]) == 0
    stage = Usd.Stage.Open(str(output))
    assert stage.GetTimeCodesPerSecond() == stage.GetFramesPerSecond() == 24.0
    assert list(read_gaussian_usd(output)["time_codes"]) == [0, 3, 6]


# ------------------------------------------------------------------------------------------------------------------
# The 3DGS .ply, read by plyfile.

STANDARD_3DGS_NAMES = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]


@pytest.mark.parametrize("sh_degree", [0, 3])
def test_canonical_ply_reads_in_plyfile_with_3dgs_attributes(tmp_path, sh_degree):
    plyfile = pytest.importorskip("plyfile")  # in the test extra
    generator = torch.Generator().manual_seed(sh_degree)
    count = 57
    gaussians = GaussianModel(torch.randn(count, 3, generator=generator),
                              torch.rand(count, 3, generator=generator),
                              0.005 + 0.05 * torch.rand(count, 3, generator=generator), sh_degree=sh_degree)
    with torch.no_grad():  # every raw parameter random, the quaternions far from unit length
        gaussians.quats.copy_(3.0 * torch.randn(count, 4, generator=generator))
        gaussians.opacity_logits.copy_(4.0 * torch.randn(count, generator=generator))
        gaussians.sh_dc.copy_(torch.randn(count, 1, 3, generator=generator))
        gaussians.sh_rest.normal_(0.0, 0.3, generator=generator)
    path = tmp_path / "canonical.ply"
    write_canonical_ply(gaussians, path)  # what warpavatar-fit writes

    ply = plyfile.PlyData.read(str(path))
    assert not ply.text and ply.byte_order == "<"
    assert [element.name for element in ply.elements] == ["vertex"]
    vertex = ply["vertex"]
    rest_count = 3 * ((sh_degree + 1) ** 2 - 1)
    expected_names = (STANDARD_3DGS_NAMES + [f"f_rest_{i}" for i in range(rest_count)]
                      + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])
    assert [p.name for p in vertex.properties] == expected_names
    assert all(p.val_dtype in ("f4", "float", "float32") for p in vertex.properties)
    assert vertex.count == count

    def column(*names):
        return np.stack([np.asarray(vertex[n], dtype=np.float64) for n in names], axis=-1)

    model = {name: getattr(gaussians, name).detach().double().numpy()
             for name in ("means", "log_scales", "quats", "opacity_logits", "sh_dc", "sh_rest")}
    np.testing.assert_array_equal(column("x", "y", "z"), model["means"].astype(np.float32))
    assert not column("nx", "ny", "nz").any()
    np.testing.assert_array_equal(column("f_dc_0", "f_dc_1", "f_dc_2"), model["sh_dc"][:, 0].astype(np.float32))
    if rest_count:  # channel-major: all red rest coefficients, then green, then blue
        rest = column(*[f"f_rest_{i}" for i in range(rest_count)]).reshape(count, 3, -1).transpose(0, 2, 1)
        np.testing.assert_array_equal(rest, model["sh_rest"].astype(np.float32))
    # the activations' inverses: logit opacity, log scales, unit quaternions (w, x, y, z)
    # (the writer takes float32 opacities: rounding p by one float32 step moves the logit by step / (p (1 - p)))
    opacity = 1 / (1 + np.exp(-model["opacity_logits"]))
    tolerance = 2 * np.spacing(opacity.astype(np.float32)) / (opacity * (1 - opacity)) + 1e-6
    assert (np.abs(column("opacity")[:, 0] - model["opacity_logits"]) <= tolerance).all()
    assert np.median(tolerance) < 1e-5
    np.testing.assert_allclose(column("scale_0", "scale_1", "scale_2"), model["log_scales"], atol=1e-5)
    rotations = column("rot_0", "rot_1", "rot_2", "rot_3")
    np.testing.assert_allclose(np.linalg.norm(rotations, axis=-1), 1.0, atol=1e-6)
    np.testing.assert_allclose(rotations, model["quats"] / np.linalg.norm(model["quats"], axis=-1, keepdims=True),
                               atol=1e-6)


def test_motion_time_codes():
    from warpavatar.io.animation import motion_time_codes

    assert motion_time_codes(np.array([6, 9, 12, 20], dtype=np.int32)).tolist() == [0, 3, 6, 14]
    assert motion_time_codes(np.array([5])).tolist() == [0]
    assert motion_time_codes(np.array([4, 2, 7])).tolist() == [0, 1, 2]  # not increasing: one per row
    assert motion_time_codes(np.array([3, 3])).tolist() == [0, 1]
