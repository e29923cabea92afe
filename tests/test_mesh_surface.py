"""Tests of the mesh export's surface: the TSDF kernel against its plain-torch reference, and
``warpavatar.mesh.surface.extract_surface`` on views of spheres rendered exactly (ray-cast), and on a small avatar's
renders."""

import numpy as np
import pytest
import torch

from warpavatar import ops
from warpavatar._torch_impl import tsdf as reference
from warpavatar.data import Skeleton
from warpavatar.mesh import surface
from warpavatar.mesh.mesh_data import CanonicalView
from warpavatar.mesh.views import view_cameras


def _random_views(generator: torch.Generator, *, count: int, height: int, width: int, device):
    """Cameras on a ring around the origin looking at it, and images whose depths straddle a unit cube's."""
    from warpavatar.mesh.views import _look_at

    matrices = []
    for index in range(count):
        angle = 2.0 * np.pi * index / count
        eye = np.array([2.0 * np.cos(angle), 2.0 * np.sin(angle), 0.4 * (index % 2) - 0.2])
        matrices.append(_look_at(eye, np.zeros(3), np.array([0.0, 0.0, 1.0])))
    world_to_camera = torch.tensor(np.stack(matrices), dtype=torch.float32)
    K = torch.tensor([[26.0, 0.3, (width - 1) / 2], [0.0, 24.0, (height - 1) / 2], [0.0, 0.0, 1.0]])
    K = K.expand(count, 3, 3).contiguous()
    alpha = torch.rand(count, height, width, generator=generator)
    alpha = torch.where(alpha < 0.08, torch.zeros_like(alpha), 0.3 + 0.7 * alpha)  # some background, mostly not
    depth = 1.4 + 1.2 * torch.rand(count, height, width, generator=generator)
    depth[alpha < 0.5] = float("inf")
    color = torch.rand(count, height, width, 3, generator=generator) * alpha[..., None]
    return [t.to(device) for t in (depth, alpha, color, K, world_to_camera)]


def test_integrate_tsdf_matches_the_reference(device):
    generator = torch.Generator().manual_seed(3)
    inputs = _random_views(generator, count=6, height=20, width=24, device=device)
    grid = ((-0.6, -0.55, -0.5), 0.05, (23, 22, 21))
    ours = ops.integrate_tsdf(*inputs, *grid, truncation=0.15)
    theirs = reference.integrate_tsdf(*inputs, *grid, truncation=0.15)
    for name, a, b in zip(("tsdf", "weight", "color"), ours, theirs):
        assert a.shape == b.shape and a.device == b.device, name
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5, msg=name)
    tsdf, weight, _ = ours
    # every kind of voxel occurs: carved or unseen (+truncation, no weight), fused, and occluded in every view
    assert (weight > 0).any() and ((weight == 0) & (tsdf == 0.15)).any() and ((weight == 0) & (tsdf == -0.15)).any()
    assert (tsdf.abs() <= 0.15 + 1e-6).all()


def test_integrate_tsdf_edge_cases(device):
    generator = torch.Generator().manual_seed(4)
    depth, alpha, color, K, world_to_camera = _random_views(generator, count=2, height=8, width=8, device=device)
    empty = ops.integrate_tsdf(depth, alpha, color, K, world_to_camera, (0, 0, 0), 0.1, (0, 3, 3), truncation=0.2)
    assert [t.shape for t in empty] == [(0, 3, 3), (0, 3, 3), (0, 3, 3, 3)]
    none = ops.integrate_tsdf(depth[:0], alpha[:0], color[:0], K[:0], world_to_camera[:0], (0, 0, 0), 0.1,
                              (2, 2, 2), truncation=0.2)
    assert (none[0] == 0.2).all() and (none[1] == 0).all()  # seen by no view: unknown, written as empty
    with pytest.raises(ValueError, match="alpha must have shape"):
        ops.integrate_tsdf(depth, alpha[:, :4], color, K, world_to_camera, (0, 0, 0), 0.1, (2, 2, 2), truncation=0.2)
    with pytest.raises(ValueError, match="truncation"):
        ops.integrate_tsdf(depth, alpha, color, K, world_to_camera, (0, 0, 0), 0.1, (2, 2, 2), truncation=0.0)


# --- extract_surface on exact renders of spheres ----------------------------------------------------------


def _sphere_views(spheres, *, count: int, size: int, low, high) -> list[CanonicalView]:
    """Views of opaque spheres ``(centre [3], radius, rgb [3])`` from :func:`view_cameras` around the box, ray-cast:
    alpha 1 and the camera z of the nearest hit, or alpha 0 and ``inf``."""
    views = []
    pixels = np.stack(np.meshgrid(np.arange(size), np.arange(size), indexing="xy"), axis=-1).reshape(-1, 2)
    for K, world_to_camera in view_cameras(np.asarray(low), np.asarray(high), np.array([0.0, 0.0, 1.0]),
                                           count=count, size=size):
        rays = np.c_[(pixels - K[:2, 2]) / np.diag(K)[:2], np.ones(len(pixels))]  # camera frame, z = 1
        rotation, translation = world_to_camera[:3, :3], world_to_camera[:3, 3]
        nearest = np.full(len(pixels), np.inf)
        rgb = np.zeros((len(pixels), 3))
        for centre, radius, colour in spheres:
            c = rotation @ np.asarray(centre, np.float64) + translation
            a = (rays * rays).sum(1)
            b = rays @ c
            disc = b * b - a * (c @ c - radius * radius)
            z = np.where(disc >= 0, (b - np.sqrt(np.maximum(disc, 0.0))) / a, np.inf)  # ray parameter = camera z
            closer = z < nearest
            nearest = np.where(closer, z, nearest)
            rgb[closer] = colour
        hit = np.isfinite(nearest)
        views.append(CanonicalView(
            K.astype(np.float32), world_to_camera.astype(np.float32), size, size,
            (rgb * hit[:, None]).reshape(size, size, 3).astype(np.float32),
            hit.reshape(size, size).astype(np.float32), nearest.reshape(size, size).astype(np.float32)))
    return views


BODY = (np.array([0.0, 0.0, 1.0]), 0.3, (0.9, 0.4, 0.1))
NEAR_BONE = (np.array([0.0, 0.0, 1.55]), 0.06, (0.1, 0.8, 0.2))  # a small part apart from the body, on a bone
FLOATER = (np.array([0.62, 0.0, 1.45]), 0.05, (0.2, 0.2, 0.9))  # small and far from every bone


@pytest.fixture(scope="module")
def sphere_scene():
    skeleton = Skeleton(["spine", "head"], [-1, 0], [[0.0, 0.0, 0.8], [0.0, 0.0, 1.2]],
                        [[0.0, 0.0, 1.2], [0.0, 0.0, 1.6]])
    views = _sphere_views([BODY, NEAR_BONE, FLOATER], count=24, size=128, low=(-0.4, -0.4, 0.6),
                          high=(0.7, 0.4, 1.65))
    return skeleton, views


def test_sphere_surface_is_watertight_close_and_decimated(sphere_scene):
    skeleton, views = sphere_scene
    mesh = surface.extract_surface(views, skeleton=skeleton, triangles=3000)
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert len(mesh.faces) <= 3000
    assert mesh.volume > 0  # wound outwards
    parts = mesh.split(only_watertight=False)
    assert len(parts) == 2  # the body and the part on a bone; the floater is dropped
    body = max(parts, key=lambda part: part.area)
    distance = np.linalg.norm(body.vertices - BODY[0], axis=1) - BODY[1]
    low, high = surface._hull_box(views, None)
    voxel = surface.default_voxel_size(views, low, high)
    assert np.abs(distance).max() < 2.0 * voxel, (np.abs(distance).max(), voxel)  # 1.1 voxels when written
    assert abs(np.median(distance)) < 0.5 * voxel
    assert np.linalg.norm(mesh.vertices - FLOATER[0], axis=1).min() > 2 * FLOATER[1]
    colours = np.asarray(mesh.visual.vertex_colors)[:, :3].astype(float) / 255.0
    on_body = np.linalg.norm(mesh.vertices - BODY[0], axis=1) < BODY[1] + 0.05
    assert np.abs(np.median(colours[on_body], axis=0) - BODY[2]).max() < 0.05


def test_without_a_skeleton_small_components_are_dropped(sphere_scene):
    _, views = sphere_scene
    mesh = surface.extract_surface(views, triangles=2000)
    assert mesh.is_watertight and len(mesh.split(only_watertight=False)) == 1
    # a voxel budget below the default's count coarsens the grid to fit it
    coarse = surface.extract_surface(views, triangles=2000, max_voxels=20_000)
    assert coarse.metadata["voxel_size"] > 1.2 * mesh.metadata["voxel_size"] and coarse.is_watertight
    with pytest.raises(ValueError, match="max_voxels"):
        surface.extract_surface(views, max_voxels=0)


def test_extract_surface_rejects_bad_views(sphere_scene):
    _, views = sphere_scene
    with pytest.raises(ValueError, match="no views"):
        surface.extract_surface([])
    with pytest.raises(ValueError, match="triangles"):
        surface.extract_surface(views, triangles=2)
    blank = [CanonicalView(v.K, v.world_to_camera, v.width, v.height, np.zeros_like(v.color), np.zeros_like(v.alpha),
                           np.full_like(v.depth, np.inf)) for v in views[:6]]
    with pytest.raises(ValueError, match="nothing to make a surface of"):
        surface.extract_surface(blank)


def test_manifold_repair_splits_a_pinched_edge():
    """Two boxes touching along one edge (a pinch: four faces on it) become two closed sheets."""
    import trimesh

    first = trimesh.creation.box(extents=(1, 1, 1))
    second = first.copy()
    second.apply_translation((1, 1, 0))  # touches the first along the edge x = y = 0.5
    merged = trimesh.util.concatenate([first, second])
    merged.merge_vertices()
    vertices, faces = np.asarray(merged.vertices), np.asarray(merged.faces, dtype=np.int64)
    assert not trimesh.Trimesh(vertices, faces, process=False).is_watertight
    vertices, faces = surface._manifold(vertices, faces)
    repaired = trimesh.Trimesh(vertices, faces, process=False)
    assert repaired.is_watertight and repaired.is_winding_consistent
    assert len(repaired.split(only_watertight=True)) == 2


# --- extract_surface on a small avatar's renders ------------------------------------------------------------


def test_small_avatar_renders_give_a_closed_mesh(avatar_dir):
    from warpavatar.mesh.views import render_canonical_views
    from warpavatar.model import Avatar

    avatar = Avatar.load(avatar_dir / "avatar.pt")
    views = render_canonical_views(avatar, count=12, size=96)
    mesh = surface.extract_surface(views, skeleton=avatar.skeleton, triangles=1500)
    assert mesh.is_watertight and len(mesh.faces) <= 1500 and mesh.volume > 0
    means = avatar.gaussians.means.detach().numpy()
    low, high = means.min(0) - 0.1, means.max(0) + 0.1
    assert (mesh.bounds[0] >= low).all() and (mesh.bounds[1] <= high).all()


def test_fit_silhouettes_brings_a_posed_surface_onto_the_views_silhouettes():
    import trimesh

    from warpavatar.geometry import quat_to_matrix

    # the views see a sphere of radius 0.3 about a posed centre; the surface is one of 0.33 about the canonical
    # centre, which a pose (a rotation and a translation, as skinning gives every vertex) carries to the views
    radius, canonical_centre = 0.3, np.array([0.0, 0.0, 1.0])
    rotation = quat_to_matrix(torch.nn.functional.normalize(torch.tensor([[0.9, 0.2, -0.3, 0.1]]), dim=1))[0]
    translation = torch.tensor([0.4, -0.2, 0.1])
    posed_centre = (rotation.double() @ torch.as_tensor(canonical_centre) + translation.double()).numpy()
    views = _sphere_views([(posed_centre, radius, (0.5, 0.5, 0.5))], count=16, size=160,
                          low=posed_centre - 0.45, high=posed_centre + 0.45)
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=radius + 0.03)
    vertices, faces = np.asarray(sphere.vertices) + canonical_centre, np.asarray(sphere.faces)
    pose = torch.cat([rotation, translation[:, None]], dim=1).expand(1, vertices.shape[0], 3, 4)
    voxel = 0.01
    moved = surface.fit_silhouettes(vertices, faces, views, voxel_size=voxel, rounds=8, poses=pose,
                                    view_poses=torch.zeros(len(views), dtype=torch.long))
    before = np.linalg.norm(vertices - canonical_centre, axis=1) - radius
    after = np.linalg.norm(moved - canonical_centre, axis=1) - radius
    assert np.median(before) == pytest.approx(0.03)
    assert abs(np.median(after)) < 0.4 * voxel and np.percentile(np.abs(after), 95) < voxel, \
        (np.median(after), np.percentile(np.abs(after), 95))
    # the moves are along the normals: the directions from the centre stay
    directions = lambda points: (points - canonical_centre) / np.linalg.norm(points - canonical_centre, axis=1,
                                                                             keepdims=True)
    assert np.abs(directions(moved) - directions(vertices)).max() < 0.02
    with pytest.raises(ValueError, match="poses must be"):
        surface.fit_silhouettes(vertices, faces, views, voxel_size=voxel, poses=pose, view_poses=[0])
