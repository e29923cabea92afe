"""USD export of animated Gaussians: every authored array read back with pxr, both layouts, UsdSkel, and the
temporary-file behaviour."""

import os
import re
from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("pxr")  # usd-core is a dependency; skip cleanly where it is absent (the GPU machine)

from pxr import Gf, Sdf, Usd, UsdGeom, UsdSkel, UsdVol

from warpavatar.io.usd import GaussianUsdWriter, read_gaussian_usd

SH_C0 = 0.28209479177387814


def random_animation(seed: int, *, count: int = 40, frames: int = 3, sh_degree: int = 2):
    rng = np.random.default_rng(seed)
    static = {
        "opacities": rng.uniform(0.0, 1.0, size=count).astype(np.float32),
        "sh_coeffs": rng.normal(size=(count, (sh_degree + 1) ** 2, 3)).astype(np.float32),
    }
    per_frame = [{
        "positions": rng.normal(size=(count, 3)).astype(np.float32),
        "orientations": rng.normal(size=(count, 4)).astype(np.float32),
        "scales": np.exp(rng.normal(-2.0, 0.7, size=(count, 3))).astype(np.float32),
    } for _ in range(frames)]
    return static, per_frame


def random_rigid(rng, joint_count: int) -> np.ndarray:
    matrices = np.tile(np.eye(4), (joint_count, 1, 1))
    q, _ = np.linalg.qr(rng.normal(size=(joint_count, 3, 3)))
    q *= np.sign(np.linalg.det(q))[:, None, None]  # proper rotations
    matrices[:, :3, :3] = q
    matrices[:, :3, 3] = rng.normal(size=(joint_count, 3))
    return matrices


def brute_force_extent(frame: dict) -> np.ndarray:
    """Box of 3-sigma ellipsoid surfaces sampled densely (independent of the writer's closed form)."""
    q = frame["orientations"].astype(np.float64)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    rotations = np.stack([np.array(Gf.Matrix3d(Gf.Rotation(Gf.Quatd(*row)))).T for row in q])
    theta, phi = np.meshgrid(np.linspace(0, np.pi, 121), np.linspace(0, 2 * np.pi, 241), indexing="ij")
    directions = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], -1)
    directions = directions.reshape(-1, 3)
    surface = np.einsum("nij,nj,mj->nmi", rotations, 3 * frame["scales"].astype(np.float64), directions)
    surface += frame["positions"][:, None, :]
    return np.stack([surface.min(axis=(0, 1)), surface.max(axis=(0, 1))])


@pytest.mark.parametrize("layout", ["particlefield", "points"])
@pytest.mark.parametrize("seed", [0, 1])
def test_round_trip_every_array(tmp_path, layout, seed):
    static, frames = random_animation(seed)
    time_codes = [3, 4, 9]
    path = tmp_path / "anim.usdc"
    with GaussianUsdWriter(path, layout=layout, gaussian_count=40, sh_degree=2, fps=24.0, up_axis="Y",
                           meters_per_unit=0.01, prim_path="/Character/Splats", **static) as writer:
        for time_code, frame in zip(time_codes, frames):
            writer.write_frame(time_code, **frame)
    assert sorted(os.listdir(tmp_path)) == ["anim.usdc"]

    data = read_gaussian_usd(path)
    assert data["layout"] == layout and data["prim_path"] == "/Character/Splats"
    np.testing.assert_array_equal(data["time_codes"], time_codes)
    for t, frame in enumerate(frames):
        for name in ("positions", "orientations", "scales"):
            np.testing.assert_array_equal(data[name][t], frame[name], err_msg=name)
        extent = data["extent"][t]
        reference = brute_force_extent(frame)
        if layout == "particlefield":
            np.testing.assert_allclose(extent, reference, atol=2e-3 * np.abs(reference).max())
        else:  # also holds the width spheres
            assert (extent[0] <= reference[0] + 1e-5).all() and (extent[1] >= reference[1] - 1e-5).all()
    np.testing.assert_array_equal(data["opacities"], static["opacities"])
    np.testing.assert_array_equal(data["sh_coeffs"], static["sh_coeffs"])
    assert data["sh_degree"] == 2
    assert data["fps"] == 24.0 and data["frames_per_second"] == 24.0
    assert data["up_axis"] == "Y" and data["meters_per_unit"] == 0.01
    assert data["start_time_code"] == 3 and data["end_time_code"] == 9

    # Independent checks straight through pxr.
    stage = Usd.Stage.Open(str(path))
    assert stage.GetDefaultPrim().GetPath() == Sdf.Path("/Character")
    assert stage.GetDefaultPrim().GetTypeName() == "Xform"
    prim = stage.GetPrimAtPath("/Character/Splats")
    colors = np.asarray(UsdGeom.Gprim(prim).GetDisplayColorAttr().Get())
    np.testing.assert_allclose(colors, np.clip(0.5 + SH_C0 * static["sh_coeffs"][:, 0], 0, 1), atol=1e-6)
    opacity = np.asarray(UsdGeom.Gprim(prim).GetDisplayOpacityAttr().Get())
    np.testing.assert_array_equal(opacity, static["opacities"])
    if layout == "particlefield":
        assert prim.GetTypeName() == "ParticleField3DGaussianSplat"
        splats = UsdVol.ParticleField3DGaussianSplat(prim)
        for schema in ("ParticleFieldPositionAttributeAPI", "ParticleFieldOrientationAttributeAPI",
                       "ParticleFieldScaleAttributeAPI", "ParticleFieldOpacityAttributeAPI",
                       "ParticleFieldSphericalHarmonicsAttributeAPI", "ParticleFieldKernelGaussianEllipsoidAPI"):
            assert schema in prim.GetAppliedSchemas()
        positions, orientations, scales = (splats.GetPositionsAttr(), splats.GetOrientationsAttr(),
                                           splats.GetScalesAttr())
        sh_attribute = splats.GetRadianceSphericalHarmonicsCoefficientsAttr()
        assert splats.GetRadianceSphericalHarmonicsDegreeAttr().Get() == 2
        np.testing.assert_array_equal(np.asarray(splats.GetOpacitiesAttr().Get()), static["opacities"])
    else:
        assert prim.GetTypeName() == "Points"
        points = UsdGeom.Points(prim)
        positions = points.GetPointsAttr()
        orientations = prim.GetAttribute("primvars:orientations")
        scales = prim.GetAttribute("primvars:scales")
        sh_attribute = prim.GetAttribute("primvars:sphericalHarmonicsCoefficients")
        assert prim.GetAttribute("primvars:sphericalHarmonicsDegree").Get() == 2
        assert UsdGeom.Primvar(orientations).GetInterpolation() == "vertex"
        for t, time_code in enumerate(time_codes):
            widths = np.asarray(points.GetWidthsAttr().Get(time_code))
            np.testing.assert_allclose(widths, 2 * frames[t]["scales"].max(axis=1), rtol=1e-7)
    # SH: per particle, its (d+1)^2 RGB coefficients contiguous.
    flat = np.asarray(sh_attribute.Get())
    np.testing.assert_array_equal(flat[9 * 5 + 4], static["sh_coeffs"][5, 4])
    assert sh_attribute.GetMetadata("interpolation") == "vertex" and sh_attribute.GetMetadata("elementSize") == 9
    # Quaternion order: Gf stores the real part apart.
    q = orientations.Get(Usd.TimeCode(time_codes[1]))[7]
    w, x, y, z = frames[1]["orientations"][7]
    assert (q.GetReal(), *q.GetImaginary()) == (w, x, y, z)
    assert list(positions.GetTimeSamples()) == time_codes
    # Defaults (no time) equal the first frame, for time-less readers.
    np.testing.assert_array_equal(np.asarray(positions.Get()), frames[0]["positions"])
    np.testing.assert_array_equal(np.asarray(scales.Get()), frames[0]["scales"])
    np.testing.assert_array_equal(np.asarray(UsdGeom.Boundable(prim).GetExtentAttr().Get()), data["extent"][0])


def test_skeleton_animation_matches_bone_transforms(tmp_path):
    rng = np.random.default_rng(3)
    static, frames = random_animation(3, count=8, frames=3, sh_degree=0)
    skeleton = {"names": ["hips", "spine", "head", "left leg", "left leg"[:4] + "_leg"],
                "parents": np.array([-1, 0, 1, 0, 0]),
                "heads": rng.normal(size=(5, 3))}
    bones = [random_rigid(rng, 5) for _ in frames]
    path = tmp_path / "rig.usd"
    with GaussianUsdWriter(path, gaussian_count=8, sh_degree=0, skeleton=skeleton, **static) as writer:
        for t, frame in enumerate(frames):
            writer.write_frame(t, joint_transforms=torch.from_numpy(bones[t]), **frame)
    data = read_gaussian_usd(path)
    assert data["joint_names"] == skeleton["names"]
    assert data["joint_paths"] == ["hips", "hips/spine", "hips/spine/head", "hips/left_leg", "hips/left_leg_1"]
    # usd-core's own UsdSkel evaluation gives back the bone transforms.
    np.testing.assert_allclose(data["joint_transforms"], np.stack(bones), atol=2e-5)
    stage = Usd.Stage.Open(str(path))
    skeleton_prim = UsdSkel.Skeleton(stage.GetPrimAtPath("/Avatar/Rig/Skeleton"))
    bind = np.asarray(skeleton_prim.GetBindTransformsAttr().Get())
    np.testing.assert_allclose(bind[:, 3, :3], skeleton["heads"])  # row-vector matrices: translation row
    rest = np.asarray(skeleton_prim.GetRestTransformsAttr().Get())
    np.testing.assert_allclose(rest[2, 3, :3], skeleton["heads"][2] - skeleton["heads"][1])
    assert stage.GetPrimAtPath("/Avatar/Rig").GetTypeName() == "SkelRoot"
    assert UsdSkel.Topology(skeleton_prim.GetJointsAttr().Get()).Validate()[0]


def test_temporary_file_and_abort(tmp_path):
    static, frames = random_animation(4, count=10, frames=3)
    path = tmp_path / "out.usdc"
    writer = GaussianUsdWriter(path, gaussian_count=10, sh_degree=2, flush_every=1, **static)
    temporary = Path(writer.temporary_path)
    # a name of its own beside the output, the crate suffix last
    assert temporary.parent == tmp_path
    assert re.fullmatch(rf"out\.tmp-{os.getpid()}-[0-9a-f]{{12}}\.usdc", temporary.name)
    sizes = []
    for t, frame in enumerate(frames):
        writer.write_frame(t, **frame)
        sizes.append(temporary.stat().st_size)
        assert not path.exists()
    assert sizes[0] < sizes[1] < sizes[2]  # saved after every frame
    assert writer.close() == str(path)
    assert sorted(os.listdir(tmp_path)) == ["out.usdc"]
    with pytest.raises(RuntimeError, match="closed"):
        writer.write_frame(5, **frames[0])

    original = path.read_bytes()
    with pytest.raises(KeyError, match="boom"):
        with GaussianUsdWriter(path, gaussian_count=10, sh_degree=2, **static) as writer:
            writer.write_frame(0, **frames[0])
            assert Path(writer.temporary_path).exists()
            raise KeyError("boom")
    assert sorted(os.listdir(tmp_path)) == ["out.usdc"] and path.read_bytes() == original
    # An invalid frame inside the block aborts the same way.
    with pytest.raises(ValueError, match="positions"):
        with GaussianUsdWriter(path, gaussian_count=10, sh_degree=2, **static) as writer:
            writer.write_frame(0, **frames[0])
            writer.write_frame(1, **{**frames[1], "positions": frames[1]["positions"][:5]})
    assert sorted(os.listdir(tmp_path)) == ["out.usdc"] and path.read_bytes() == original
    with pytest.raises(ValueError, match="no frame"):
        with GaussianUsdWriter(path, gaussian_count=10, sh_degree=2, **static):
            pass
    assert sorted(os.listdir(tmp_path)) == ["out.usdc"] and path.read_bytes() == original
    # A writer dropped without close() removes its temporary file too.
    writer = GaussianUsdWriter(path, gaussian_count=10, sh_degree=2, **static)
    writer.write_frame(0, **frames[0])
    assert Path(writer.temporary_path).exists()
    del writer
    assert sorted(os.listdir(tmp_path)) == ["out.usdc"] and path.read_bytes() == original
    # Two writers of one name (and of .usd beside .usdc) never share a temporary file.
    first = GaussianUsdWriter(path, gaussian_count=10, sh_degree=2, **static)
    second = GaussianUsdWriter(tmp_path / "out.usd", gaussian_count=10, sh_degree=2, **static)
    assert first.temporary_path != second.temporary_path
    first.abort()
    second.abort()


def test_empty_gaussians(tmp_path):
    path = tmp_path / "empty.usdc"
    empty = np.zeros((0, 3), np.float32)
    with GaussianUsdWriter(path, layout="points", gaussian_count=0, sh_degree=0, opacities=np.zeros(0),
                           sh_coeffs=np.zeros((0, 1, 3))) as writer:
        writer.write_frame(0, positions=empty, orientations=np.zeros((0, 4)), scales=empty)
    data = read_gaussian_usd(path)
    assert data["positions"].shape == (1, 0, 3)
    np.testing.assert_array_equal(data["extent"][0], np.zeros((2, 3)))


def test_errors(tmp_path):
    static, frames = random_animation(5, count=6, frames=2, sh_degree=1)
    good = dict(gaussian_count=6, sh_degree=1, **static)
    cases = [
        (dict(path=tmp_path / "a.usda"), ".usdc or .usd"),
        (dict(layout="mesh"), "layout"),
        (dict(sh_degree=2), "sh_coeffs must have shape"),
        (dict(opacities=static["opacities"] * 2), r"\[0, 1\]"),
        (dict(up_axis="X"), "up_axis"),
        (dict(fps=0), "fps"),
        (dict(prim_path="/Gaussians"), "two components"),
        (dict(prim_path="not a path"), "prim path"),
        (dict(skeleton={"names": ["a", "b"], "parents": np.array([1, -1]), "heads": np.zeros((2, 3))}),
         "parent listed before"),
    ]
    for change, message in cases:
        arguments = {"path": tmp_path / "x.usdc", **good, **change}
        with pytest.raises((ValueError, TypeError), match=message):
            GaussianUsdWriter(arguments.pop("path"), **arguments)
        assert not (tmp_path / "x.tmp.usdc").exists()

    skeleton = {"names": ["a", "b"], "parents": np.array([-1, 0]), "heads": np.zeros((2, 3))}
    with GaussianUsdWriter(tmp_path / "x.usdc", skeleton=skeleton, **good) as writer:
        with pytest.raises(ValueError, match="joint_transforms is required"):
            writer.write_frame(0, **frames[0])
        squashed = np.tile(np.eye(4), (2, 1, 1))
        squashed[1, 0, 0] = 2.0
        with pytest.raises(ValueError, match="rigid"):
            writer.write_frame(0, joint_transforms=squashed, **frames[0])
        writer.write_frame(0, joint_transforms=np.tile(np.eye(4), (2, 1, 1)), **frames[0])
        with pytest.raises(ValueError, match="must increase"):
            writer.write_frame(0, joint_transforms=np.tile(np.eye(4), (2, 1, 1)), **frames[1])
        with pytest.raises(TypeError, match="int"):
            writer.write_frame(1.5, joint_transforms=np.tile(np.eye(4), (2, 1, 1)), **frames[1])
        bad = {**frames[1], "scales": -frames[1]["scales"]}
        with pytest.raises(ValueError, match="scales must be > 0"):
            writer.write_frame(1, joint_transforms=np.tile(np.eye(4), (2, 1, 1)), **bad)
        bad = {**frames[1], "orientations": np.full((6, 4), np.inf, np.float32)}
        with pytest.raises(ValueError, match="non-finite"):
            writer.write_frame(1, joint_transforms=np.tile(np.eye(4), (2, 1, 1)), **bad)
    with GaussianUsdWriter(tmp_path / "y.usdc", **good) as writer:
        with pytest.raises(ValueError, match="no skeleton"):
            writer.write_frame(0, joint_transforms=np.tile(np.eye(4), (2, 1, 1)), **frames[0])
        writer.write_frame(0, **frames[0])
    with pytest.raises(ValueError, match="cannot open"):
        read_gaussian_usd(tmp_path / "absent.usdc")
