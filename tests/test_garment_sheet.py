"""The template-free garment sheet (warpavatar.sim.garment_sheet): synthetic garments sampled with noise and points
inside them, the sheet against the true outer surface, its pinned waistband, open hem, open sides for a partial
garment, outward normals and its files."""

import math

import numpy as np
import pytest
import torch
import trimesh

from warpavatar.sim.garment_sheet import build_garment_sheet

ORIGIN = np.array([0.0, 0.0, 1.0])  # the attachment joint; the garment hangs along -z
DOWN = np.array([0.0, 0.0, -1.0])


def _profile_points(seed, heights, radii, count=5000, *, noise=0.003, interior=0.2, angles=(-math.pi, math.pi),
                    origin=ORIGIN):
    """Points of a surface of revolution about -z through ``origin``, meridian polyline (height, radius), sampled by
    area, with 3D noise [m]; a share ``interior`` of them moved inside the garment along its inward normal by 1-8 cm
    (Gaussians inside the cloth, its far side)."""
    rng = np.random.default_rng(seed)
    heights, radii = np.asarray(heights, float), np.asarray(radii, float)
    lengths = np.hypot(np.diff(heights), np.diff(radii))
    areas = lengths * 0.5 * (radii[1:] + radii[:-1])
    piece = rng.choice(len(lengths), size=count, p=areas / areas.sum())
    s = rng.random(count)
    h = heights[piece] + s * (heights[piece + 1] - heights[piece])
    r = radii[piece] + s * (radii[piece + 1] - radii[piece])
    dh, dr = np.diff(heights)[piece] / lengths[piece], np.diff(radii)[piece] / lengths[piece]
    depth = np.where(rng.random(count) < interior, rng.uniform(0.01, 0.08, count), 0.0)
    h, r = h + depth * dr, np.maximum(r - depth * dh, 0.0)
    theta = rng.uniform(*angles, size=count)
    points = np.asarray(origin) + np.stack([r * np.cos(theta), r * np.sin(theta), -h], axis=1)
    return points + noise * rng.standard_normal(points.shape)


def _distance_to_profile(vertices, heights, radii, origin=ORIGIN):
    """Distance [m] of each vertex to the surface of revolution (in its meridian plane)."""
    q = vertices - origin
    plane = np.stack([-q[:, 2], np.hypot(q[:, 0], q[:, 1])], axis=1)
    best = np.full(len(plane), np.inf)
    for i in range(len(heights) - 1):
        a, b = np.array([heights[i], radii[i]]), np.array([heights[i + 1], radii[i + 1]])
        t = np.clip((plane - a) @ (b - a) / ((b - a) @ (b - a)), 0.0, 1.0)
        best = np.minimum(best, np.linalg.norm(plane - (a + t[:, None] * (b - a)), axis=1))
    return best


def _check_sheet(sheet, *, rings, columns, origin=ORIGIN, axis=DOWN):
    assert sheet.vertices.shape == (rings * columns, 3) and sheet.faces.shape == (2 * (rings - 1) * (columns - (
        0 if not sheet.is_open else 1)), 3)
    # the waistband is ring 0, pinned, and at the top
    assert np.array_equal(np.sort(sheet.pinned), np.nonzero(sheet.ring_ids == 0)[0])
    assert len(sheet.pinned) == columns
    heights = (sheet.vertices - origin) @ axis
    assert heights[sheet.pinned].mean() < heights[sheet.hem].mean()
    # every edge is shared by two triangles but the waistband's, the hem's and an open sheet's sides
    boundary = sheet.boundary_edges()
    segments = columns if not sheet.is_open else columns - 1
    assert len(boundary) == 2 * segments + (2 * (rings - 1) if sheet.is_open else 0)
    hem = set(sheet.hem.tolist())
    assert sum(a in hem and b in hem for a, b in boundary) == segments  # the hem is open
    # outward normals (away from the axis, up for a flared sheet), UVs in [0, 1]
    mesh = sheet.mesh
    radial = mesh.triangles_center - origin
    radial -= np.outer(radial @ axis, axis)
    radial /= np.linalg.norm(radial, axis=1, keepdims=True)
    outward = -math.sin(sheet.cone_angle) * axis + math.cos(sheet.cone_angle) * radial
    assert np.mean(np.sum(mesh.face_normals * outward, axis=1) > 0.5) > 0.98
    assert sheet.uv.min() >= 0.0 and sheet.uv.max() <= 1.0
    assert np.allclose(sheet.uv[sheet.pinned, 1], 0.0) and np.allclose(sheet.uv[sheet.hem, 1], 1.0)
    assert np.all(mesh.area_faces > 1e-8)


SHAPES = {
    # name: (heights, radii, angles, expected cone angle [deg] or None)
    "skirt": ([0.02, 0.5], [0.16, 0.30], (-math.pi, math.pi), math.degrees(math.atan2(0.14, 0.48))),
    "long dress": ([0.0, 0.15, 0.25, 0.6, 1.1], [0.14, 0.18, 0.19, 0.18, 0.30], (-math.pi, math.pi), None),
    "skirt wider than long": ([0.0, 0.12], [0.15, 0.55], (-math.pi, math.pi), math.degrees(math.atan2(0.4, 0.12))),
}


@pytest.mark.parametrize("name", list(SHAPES))
def test_a_closed_sheet_lies_on_the_garments_outer_surface(name):
    heights, radii, angles, cone = SHAPES[name]
    points = _profile_points(1, heights, radii, angles=angles)
    sheet = build_garment_sheet(points, axis_origin=ORIGIN, axis_direction=DOWN, rings=16, segments=32)
    assert not sheet.is_open
    _check_sheet(sheet, rings=16, columns=32)
    distance = _distance_to_profile(sheet.vertices, heights, radii)
    # the envelope sits about 1.3 noise deviations outside the mean surface (its 90 % quantile), the rest is fit
    assert np.median(distance) < 0.006 and distance.max() < 0.015, (np.median(distance), distance.max())
    if cone is not None:
        assert abs(math.degrees(sheet.cone_angle) - cone) < 2.0
    # the sheet spans the garment: waistband near its top, hem near its bottom
    q = sheet.vertices - ORIGIN
    top, hem = (-q[sheet.pinned, 2]).mean(), (-q[sheet.hem, 2]).mean()
    assert abs(top - heights[0]) < 0.02 and abs(hem - heights[-1]) < 0.02


def test_coat_tails_give_an_open_sheet_over_their_span_only():
    heights, radii = [0.0, 0.6], [0.2, 0.2]
    back = (0.5 * math.pi, 1.5 * math.pi)  # the half at -x, across the angle's wrap at pi
    points = _profile_points(2, heights, radii, angles=back)
    sheet = build_garment_sheet(points, axis_origin=ORIGIN, axis_direction=DOWN, rings=12, segments=20,
                                reference_direction=(1.0, 0.0, 0.0))
    assert sheet.is_open
    _check_sheet(sheet, rings=12, columns=21)
    start, end = sheet.angle_range
    assert 170.0 < math.degrees(end - start) < 181.0
    # every vertex lies at the back, over the occupied angles
    q = sheet.vertices - ORIGIN
    assert np.all(q[:, 0] < 0.02)
    distance = _distance_to_profile(sheet.vertices, heights, radii)
    assert np.median(distance) < 0.006 and distance.max() < 0.015
    # a full ring when the garment covers almost all the way around (a narrow slit is missing points)
    slit = _profile_points(3, heights, radii, angles=(-math.pi + 0.3, math.pi - 0.3))
    assert not build_garment_sheet(slit, axis_origin=ORIGIN, axis_direction=DOWN, rings=8, segments=16).is_open


def test_a_poncho_hangs_from_a_chest_joint():
    chest = np.array([0.0, 0.1, 1.45])  # a chest joint a little in front of the axis the poncho turns about
    heights, radii = [0.05, 0.45], [0.11, 0.45]
    points = _profile_points(4, heights, radii, origin=chest)
    sheet = build_garment_sheet(torch.as_tensor(points), axis_origin=chest, axis_direction=DOWN, rings=12,
                                segments=24)
    assert not sheet.is_open
    _check_sheet(sheet, rings=12, columns=24, origin=chest)
    distance = _distance_to_profile(sheet.vertices, heights, radii, origin=chest)
    assert np.median(distance) < 0.006 and distance.max() < 0.015
    assert abs(math.degrees(sheet.cone_angle) - math.degrees(math.atan2(0.34, 0.40))) < 2.0


def test_the_sheet_is_written_for_inspection(tmp_path):
    points = _profile_points(5, [0.0, 0.4], [0.15, 0.25], count=2000)
    sheet = build_garment_sheet(points, axis_origin=ORIGIN, axis_direction=DOWN, rings=6, segments=12)
    for suffix in (".ply", ".obj"):
        path = sheet.write(tmp_path / f"sheet{suffix}")
        assert sorted(p.name for p in tmp_path.iterdir() if p.suffix == suffix) == [path.name]
        loaded = trimesh.load(path, process=False)
        assert loaded.vertices.shape == sheet.vertices.shape and loaded.faces.shape == sheet.faces.shape
        np.testing.assert_allclose(loaded.vertices, sheet.vertices, atol=1e-6)
        np.testing.assert_allclose(loaded.visual.uv, sheet.uv, atol=1e-6)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sheet.obj", "sheet.ply"]  # no material, no leftovers
    with pytest.raises(ValueError, match=r"\.ply or \.obj"):
        sheet.write(tmp_path / "sheet.stl")


@pytest.mark.parametrize("change, message", [
    ({"garment_points": np.zeros((5, 3))}, "at least"),
    ({"garment_points": np.full((100, 3), np.nan)}, "finite"),
    ({"garment_points": np.zeros((100, 2))}, r"shape \[N, 3\]"),
    ({"axis_direction": (0.0, 0.0, 0.0)}, "axis_direction must not be zero"),
    ({"rings": 1}, "rings must be an int >= 2"),
    ({"segments": 2.5}, "segments must be an int"),
    ({"envelope_quantile": 1.5}, "envelope_quantile"),
])
def test_bad_options_are_one_clear_error(change, message):
    arguments = {"garment_points": _profile_points(6, [0.0, 0.4], [0.15, 0.25], count=500), "axis_origin": ORIGIN,
                 "axis_direction": DOWN, "rings": 6, "segments": 12, **change}
    points = arguments.pop("garment_points")
    with pytest.raises(ValueError, match=message):
        build_garment_sheet(points, **arguments)
