"""The garment sheet in the animated USD (``warpavatar-animate``): a ``UsdGeom.Mesh`` beside the Gaussians whose
points are, frame by frame, the sheet the garment Gaussians were placed on; OpenUSD's validators find no error; an
avatar without a sheet writes no such prim."""

from __future__ import annotations

import math
import os

import numpy as np
import pytest
import torch
from pxr import Usd, UsdGeom

from warpavatar import data, ops
from warpavatar.cli import animate
from warpavatar.extensions.garment_sheet_part import GarmentSheetPart
from warpavatar.io.exporters import ExportOptions, exporter_for
from warpavatar.io.usd import AnimatedMesh, GaussianUsdWriter, read_gaussian_usd
from warpavatar.model import Avatar
from warpavatar.sim import Capsules

from tests.test_usd_mesh_export import validation_errors

POINT_TOLERANCE = 1e-5  # [m]
RINGS, SEGMENTS = 3, 8


def tube_sheet(centre: np.ndarray, *, radius: float, length: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A closed tube hanging down -Z from ``centre``: vertices [RINGS*SEGMENTS,3], faces [F,3] (outward normals)
    and the top ring's ids (pinned)."""
    angles = torch.arange(SEGMENTS, dtype=torch.float64) * (2 * math.pi / SEGMENTS)
    rings = []
    for ring in range(RINGS):
        height = -length * ring / (RINGS - 1)
        rings.append(torch.stack([radius * angles.cos(), radius * angles.sin(), torch.full_like(angles, height)], 1))
    vertices = (torch.cat(rings) + torch.as_tensor(centre)).float()
    faces = []
    for ring in range(RINGS - 1):
        for k in range(SEGMENTS):
            a, b = ring * SEGMENTS + k, ring * SEGMENTS + (k + 1) % SEGMENTS
            faces += [(a, a + SEGMENTS, b), (b, a + SEGMENTS, b + SEGMENTS)]
    return vertices, torch.tensor(faces, dtype=torch.int64), torch.arange(SEGMENTS)


@pytest.fixture(scope="module")
def sheet_avatar(avatar_dir):
    """A fresh copy of the test avatar with a small garment sheet (a tube about the hips, 24 vertices) holding the
    18 Gaussians closest to it; no fit."""
    avatar = Avatar.load(avatar_dir / "avatar.pt")
    skeleton = avatar.skeleton
    names = list(skeleton.names)
    legs = [names.index(n) for n in ("Hips", "UpperLegL", "UpperLegR")]
    heads = torch.as_tensor(skeleton.heads, dtype=torch.float32)
    tails = torch.as_tensor(skeleton.tails, dtype=torch.float32)
    vertices, faces, pinned = tube_sheet(skeleton.heads[legs[0]], radius=0.15, length=0.3)
    with torch.no_grad():
        weights = avatar.field.weights(vertices, avatar.field.grid_weights())
        # the garment: the 18 Gaussians closest to the tube's centre
        ids = (avatar.gaussians.means - vertices.mean(0)).norm(dim=1).argsort()[:18].sort().values
    capsules = Capsules(heads, tails, torch.full((len(names),), 0.05))
    part = GarmentSheetPart(ids, vertices, faces, pinned, weights, joint=legs[0], capsules=capsules,
                            capsule_ids=torch.tensor(legs[1:]), max_substep=1.0 / 60.0, up=tuple(skeleton.up),
                            joint_count=len(names), settle_substeps=8)
    part.bind(avatar.gaussians.means, avatar.gaussians.normalized_quats, avatar.gaussians.scales)
    avatar.add_part(part)
    return avatar


def test_the_usd_holds_the_sheet_the_gaussians_ride_on(sheet_avatar, export_motion, tmp_path):
    sheet_avatar.save(tmp_path / "avatar.pt")
    path = tmp_path / "avatar.usdc"
    motion_folder = data.demo_subject_path() / "novel_pose" / "dance_cam000"
    assert animate.main([str(tmp_path / "avatar.pt"), "--motion", str(motion_folder), "--frames", "0:5", "-o",
                         str(path), "--no-progress", "--device", "cpu"]) == 0
    assert validation_errors(path) == []
    stage = Usd.Stage.Open(os.fspath(path))
    prim = stage.GetPrimAtPath("/Avatar/Garment")
    assert prim and prim.IsA(UsdGeom.Mesh)
    mesh = UsdGeom.Mesh(prim)
    # the part as the file holds it, posed over the same frames (what deform_posed placed the Gaussians on)
    avatar = Avatar.load(tmp_path / "avatar.pt")
    part = avatar.part("garment")
    assert isinstance(part, GarmentSheetPart)
    sheets = [part.posed_sheet(posed)[0].numpy() for posed in export_motion.posed_frames(avatar)]
    assert list(mesh.GetFaceVertexCountsAttr().Get()) == [3] * part.faces.shape[0]
    np.testing.assert_array_equal(np.asarray(mesh.GetFaceVertexIndicesAttr().Get()).reshape(-1, 3),
                                  part.faces.numpy())
    gaussians = read_gaussian_usd(path)
    codes = export_motion.time_codes()
    assert list(gaussians["time_codes"]) == codes.tolist() == [0, 3, 6, 9, 12]
    assert list(mesh.GetPointsAttr().GetTimeSamples()) == codes.tolist()
    assert list(mesh.GetExtentAttr().GetTimeSamples()) == codes.tolist()
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z
    color = np.asarray(mesh.GetDisplayColorAttr().Get())
    assert color.shape == (1, 3) and ((color > 0) & (color < 1)).all()

    meters = UsdGeom.GetStageMetersPerUnit(stage)  # the avatar's units are metres
    ids = part.gaussian_ids
    g = avatar.gaussians
    with torch.no_grad():
        local = part.local_values(g.means[ids], g.normalized_quats[ids], g.scales[ids])
    for t, code in enumerate(codes):
        points = np.asarray(mesh.GetPointsAttr().Get(Usd.TimeCode(float(code))), dtype=np.float64) * meters
        np.testing.assert_allclose(points, sheets[t], atol=POINT_TOLERANCE, rtol=0)
        extent = np.asarray(mesh.GetExtentAttr().Get(Usd.TimeCode(float(code)))) * meters
        np.testing.assert_allclose(extent, [points.min(0), points.max(0)], atol=POINT_TOLERANCE)
        # and the file's garment Gaussians sit on the file's sheet
        with torch.no_grad():
            means = ops.pose_triangle_gaussians(torch.as_tensor(points / meters, dtype=torch.float32), part.faces,
                                                part.rest_area, part.triangle_ids, *local)[0]
        np.testing.assert_allclose(gaussians["positions"][t][ids.numpy()], means.numpy(), atol=1e-4, rtol=0)
    # the sheet moves: the simulated frames differ (a frozen mesh would pass the checks above trivially)
    assert np.abs(sheets[-1] - sheets[0]).max() > 1e-3


def test_an_avatar_without_a_sheet_writes_no_mesh(export_avatar, export_motion, tmp_path):
    path = tmp_path / "avatar.usdc"
    exporter_for(path).export(export_avatar, path, motion=export_motion, options=ExportOptions(progress=False))
    stage = Usd.Stage.Open(os.fspath(path))
    assert not any(prim.IsA(UsdGeom.Mesh) for prim in stage.Traverse())
    assert not stage.GetPrimAtPath("/Avatar/Garment")


def test_the_writer_checks_its_meshes(tmp_path):
    mesh = AnimatedMesh("Garment", np.array([[0, 1, 2]]), 3, (0.2, 0.3, 0.4))
    arguments = dict(gaussian_count=1, sh_degree=0, opacities=[0.5], sh_coeffs=np.zeros((1, 1, 3)))
    for bad, message in ((AnimatedMesh("Gaussians", mesh.faces, 3), "taken"),
                         (AnimatedMesh("a b", mesh.faces, 3), "identifier"),
                         (AnimatedMesh("Garment", np.array([[0, 1, 3]]), 3), "vertex ids"),
                         (AnimatedMesh("Garment", mesh.faces, 3, (2.0, 0.0, 0.0)), "0..1")):
        with pytest.raises(ValueError, match=message):
            GaussianUsdWriter(tmp_path / "bad.usdc", meshes=[bad], **arguments)
    assert os.listdir(tmp_path) == []
    frame = dict(positions=[[0, 0, 0]], orientations=[[1, 0, 0, 0]], scales=[[0.1, 0.1, 0.1]])
    with GaussianUsdWriter(tmp_path / "ok.usdc", meshes=[mesh], **arguments) as writer:
        with pytest.raises(ValueError, match="missing Garment"):
            writer.write_frame(0, **frame)
        with pytest.raises(ValueError, match=r"must have shape \[3, 3\]"):
            writer.write_frame(0, **frame, mesh_points={"Garment": np.zeros((4, 3))})
        writer.write_frame(0, **frame, mesh_points={"Garment": np.eye(3)})
    stage = Usd.Stage.Open(os.fspath(tmp_path / "ok.usdc"))
    points = UsdGeom.Mesh(stage.GetPrimAtPath("/Avatar/Garment")).GetPointsAttr()
    np.testing.assert_array_equal(np.asarray(points.Get()), np.eye(3))  # the default value: the first frame
    assert list(points.GetTimeSamples()) == [0.0]
