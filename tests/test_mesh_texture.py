"""Tests of the mesh export's UVs and texture (warpavatar.mesh.texture) and of its kernels (texture_bake): the Warp
kernels against their plain-torch references on every device, the unwrap's layout (UVs in range, charts apart,
seams split), and bakes of a sphere striped by longitude whose views are built analytically."""

import math

import numpy as np
import pytest
import torch
import trimesh

from warpavatar import ops
from warpavatar._torch_impl import texture_bake as reference
from warpavatar.mesh import texture
from warpavatar.mesh.mesh_data import CanonicalView
from warpavatar.mesh.views import view_cameras

# ---------------------------------------------------------------------------------------------------------
# kernels against their references
# ---------------------------------------------------------------------------------------------------------


def quad_layout(cells: int, generator):
    """UVs of ``cells x cells`` jittered quads, each split into two triangles along a shared diagonal (half of
    them wound the other way round in UV), with random 3D positions and normals."""
    uvs, faces = [], []
    corners = torch.tensor([[0.1, 0.1], [0.9, 0.1], [0.9, 0.9], [0.1, 0.9]])
    for row in range(cells):
        for column in range(cells):
            base = torch.tensor([column, row], dtype=torch.float32)
            quad = (base + corners + 0.08 * (torch.rand(4, 2, generator=generator) - 0.5)) / cells
            first = len(uvs) * 4
            uvs.append(quad)
            if (row + column) % 2:
                faces += [[first, first + 1, first + 2], [first, first + 2, first + 3]]
            else:
                faces += [[first + 2, first + 1, first], [first + 3, first + 2, first]]
    uvs = torch.cat(uvs)
    vertices = torch.randn(uvs.shape[0], 3, generator=generator)
    normals = torch.randn(uvs.shape[0], 3, generator=generator)
    return vertices, torch.tensor(faces, dtype=torch.int32), normals, uvs


@pytest.mark.parametrize("seed, margin", [(0, 0.0), (1, 1.5)])
def test_rasterize_uv_atlas_matches_reference(device, seed, margin):
    generator = torch.Generator().manual_seed(seed)
    vertices, faces, normals, uvs = quad_layout(5, generator)
    size = 37
    with torch.no_grad():
        actual = ops.rasterize_uv_atlas(vertices.to(device), faces.to(device), normals.to(device), uvs.to(device),
                                        size=size, margin=margin)
        expected = reference.rasterize_uv_atlas(vertices, faces, normals, uvs, size=size, margin=margin)
    actual = [value.cpu() for value in actual]
    face, expected_face = actual[0], expected[0]
    assert (expected_face >= 0).float().mean() > 0.3
    assert ((face >= 0) == (expected_face >= 0)).all()
    # a centre (about) equally near two triangles may go to either in float32; its point is the same
    same = (face == expected_face) & (face >= 0)
    assert (face != expected_face).sum() <= 4
    covered = face >= 0
    for name, value, wanted in zip(("point", "distance"), actual[2::2], expected[2::2]):
        assert torch.allclose(value[covered], wanted[covered], atol=1e-5), name
    for name, value, wanted in zip(("barycentric", "normal"), actual[1::2], expected[1::2]):
        assert torch.allclose(value[same], wanted[same], atol=1e-5), name
    assert torch.allclose(actual[1][covered].sum(dim=1), torch.ones(int(covered.sum())), atol=1e-5)
    assert (actual[1][~covered] == 0).all() and torch.isinf(actual[4][~covered]).all()
    assert (actual[4][covered] <= margin).all()


def test_rasterize_uv_atlas_gives_a_shared_edge_to_the_lower_triangle_and_a_margin_the_nearest(device):
    # a square cut along its diagonal, which runs through texel centres
    size = 16
    uvs = torch.tensor([[2.5, 2.5], [12.5, 2.5], [12.5, 12.5], [2.5, 12.5]]) / size
    vertices = torch.cat([uvs, torch.zeros(4, 1)], dim=1)
    normals = torch.tensor([[0.0, 0.0, 1.0]]).repeat(4, 1)
    diagonal = torch.arange(3, 12)
    for faces in ([[0, 1, 2], [0, 2, 3]], [[2, 1, 0], [3, 2, 0]]):
        faces = torch.tensor(faces, dtype=torch.int32)
        with torch.no_grad():
            face, _, point, _, distance = [value.cpu() for value in ops.rasterize_uv_atlas(
                vertices.to(device), faces.to(device), normals.to(device), uvs.to(device), size=size, margin=2.0)]
        assert (face[diagonal, diagonal] == 0).all() and (distance[diagonal, diagonal] == 0).all()
        inside = slice(2, 13)
        assert (distance[inside, inside] == 0).all()
        # centres up to two texels outside the square take its closest point, on its border
        centre = torch.arange(size) + 0.5
        outside_x = (2.5 - centre).clamp_min(0) + (centre - 12.5).clamp_min(0)
        to_square = (outside_x[None] ** 2 + outside_x[:, None] ** 2).sqrt()
        assert ((face >= 0) == (to_square <= 2.0)).all()
        assert torch.allclose(distance[face >= 0], to_square[face >= 0])
        assert torch.allclose(distance[0, 5], torch.tensor(2.0)) and torch.allclose(distance[1, 1], torch.tensor(2**0.5))
        assert torch.allclose(point[0, 5], torch.tensor([5.5 / size, 2.5 / size, 0.0]), atol=1e-6)
        assert torch.allclose(point[1, 1], torch.tensor([2.5 / size, 2.5 / size, 0.0]), atol=1e-6)


def random_views(count: int, size: int, generator):
    """Cameras around the unit box with random premultiplied images and the depths of a sphere of radius 0.4
    (inf off it), as the kernel's arrays."""
    cameras = view_cameras(np.full(3, -0.5), np.full(3, 0.5), np.array([0.0, 0.0, 1.0]), count=count, size=size)
    world_to_camera = torch.tensor(np.stack([c[1] for c in cameras]), dtype=torch.float32)
    intrinsics = torch.tensor(np.stack([c[0] for c in cameras]), dtype=torch.float32)
    depths = torch.stack([torch.as_tensor(sphere_view(K, matrix, size, 0.4)[2]) for K, matrix in cameras])
    alpha = 0.3 + 0.7 * torch.rand(count, size, size, 1, generator=generator)
    images = torch.cat([alpha * torch.rand(count, size, size, 3, generator=generator), alpha], dim=3)
    return world_to_camera, intrinsics, images.float(), depths.float()


@pytest.mark.parametrize("seed", [0, 1])
def test_average_view_colors_matches_reference(device, seed):
    generator = torch.Generator().manual_seed(seed)
    world_to_camera, intrinsics, images, depths = random_views(6, 24, generator)
    points = torch.randn(400, 3, generator=generator)
    points = 0.4 * points / points.norm(dim=1, keepdim=True)
    normals = points / 0.4 + 0.3 * torch.randn(400, 3, generator=generator)
    normals = normals / normals.norm(dim=1, keepdim=True)
    sizes = torch.tensor([[24, 24], [20, 24], [24, 18], [24, 24], [16, 16], [24, 24]], dtype=torch.int32)
    for image_sizes in (None, sizes):
        options = dict(depth_tolerance=0.03, min_cosine=0.05, image_sizes=image_sizes)
        with torch.no_grad():
            colors, weights = ops.average_view_colors(
                points.to(device), normals.to(device), world_to_camera.to(device), intrinsics.to(device),
                images.to(device), depths.to(device),
                **{**options, "image_sizes": None if image_sizes is None else image_sizes.to(device)})
            expected_colors, expected_weights = reference.average_view_colors(
                points, normals, world_to_camera, intrinsics, images, depths, **options)
        assert (expected_weights > 0).float().mean() > 0.4
        # a point exactly on a visibility test's threshold may be decided differently in float32: a few at most
        close = (weights.cpu() - expected_weights).abs() < 1e-4
        assert (~close).sum() <= 4
        assert torch.allclose(colors.cpu()[close], expected_colors[close], atol=1e-4)
        assert (colors.cpu()[weights.cpu() == 0] == 0).all()


def test_nearest_points_matches_reference(device):
    generator = torch.Generator().manual_seed(3)
    known = torch.randn(2000, 3, generator=generator)
    known = known / known.norm(dim=1, keepdim=True)
    queries = torch.cat([1.2 * torch.randn(300, 3, generator=generator), 40.0 + torch.randn(5, 3, generator=generator)])
    with torch.no_grad():
        nearest, distance = ops.nearest_points(known.to(device), queries.to(device))
        expected_nearest, expected_distance = reference.nearest_points(known, queries)
    assert torch.allclose(distance.cpu(), expected_distance, rtol=1e-5, atol=1e-6)
    chosen = (known[nearest.cpu()] - queries).norm(dim=1)
    assert torch.allclose(chosen, expected_distance, rtol=1e-5, atol=1e-6)
    assert (nearest.cpu() == expected_nearest).float().mean() > 0.99


def test_the_bake_ops_refuse_gradients():
    points = torch.zeros(2, 3, requires_grad=True)
    with pytest.raises(ValueError, match="no gradients"):
        ops.nearest_points(points, points)


# ---------------------------------------------------------------------------------------------------------
# unwrap
# ---------------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def sphere():
    """An icosphere of radius 0.5 (5120 triangles)."""
    mesh = trimesh.creation.icosphere(subdivisions=4, radius=0.5)
    vertices = np.asarray(mesh.vertices, dtype=np.float32)
    faces = np.asarray(mesh.faces, dtype=np.int32)
    return vertices, faces


@pytest.fixture(scope="module")
def unwrapped(sphere):
    vertices, faces = sphere
    return texture.unwrap(vertices, faces, size=256)


def chart_labels(faces: np.ndarray, vertex_count: int) -> np.ndarray:
    """[F] chart of each face: faces sharing a (split) vertex are in one chart."""
    parent = np.arange(vertex_count)

    def root(index):
        while parent[index] != index:
            parent[index] = parent[parent[index]]
            index = parent[index]
        return index

    for a, b, c in faces:
        for x, y in ((a, b), (b, c)):
            rx, ry = root(x), root(y)
            if rx != ry:
                parent[rx] = ry
    return np.array([root(face[0]) for face in faces])


def test_unwrap_splits_the_seams_and_keeps_the_surface(sphere, unwrapped):
    vertices, faces = sphere
    new_vertices, new_faces, uvs, source_vertex = unwrapped
    assert new_vertices.dtype == np.float32 and new_faces.dtype == np.int32 and uvs.dtype == np.float32
    assert source_vertex.dtype == np.int32 and new_faces.shape == faces.shape
    assert uvs.shape == (new_vertices.shape[0], 2) and source_vertex.shape == (new_vertices.shape[0],)
    assert np.array_equal(new_vertices, vertices[source_vertex])  # split copies sit where their source does
    assert np.array_equal(source_vertex[new_faces], faces)  # the same triangles, in order
    assert np.array_equal(np.unique(source_vertex), np.arange(vertices.shape[0]))
    copies = np.bincount(source_vertex)
    assert new_vertices.shape[0] > vertices.shape[0] and copies.max() >= 2  # there are seams
    # copies of one vertex are distinct in UV (else they would not have been split)
    order = np.argsort(source_vertex, kind="stable")
    split = np.flatnonzero(np.diff(source_vertex[order]) == 0)
    gaps = np.linalg.norm(uvs[order[split]] - uvs[order[split + 1]], axis=1)
    assert (gaps > 0).mean() > 0.99


def test_unwrap_packs_charts_apart_inside_the_atlas(unwrapped):
    new_vertices, new_faces, uvs, _ = unwrapped
    size = 256
    assert uvs.min() >= 0.0 and uvs.max() <= 1.0
    border = texture.GUTTER_TEXELS // 2 / size
    assert uvs.min() >= border - 1e-6 and uvs.max() <= 1.0 - border + 1e-6
    corners = uvs[new_faces].astype(np.float64)
    signed = 0.5 * ((corners[:, 1, 0] - corners[:, 0, 0]) * (corners[:, 2, 1] - corners[:, 0, 1])
                    - (corners[:, 1, 1] - corners[:, 0, 1]) * (corners[:, 2, 0] - corners[:, 0, 0]))
    area = np.abs(signed).sum()
    assert 0.2 < area < 1.0
    # no triangle folded over inside its chart (a chart may be mirrored as a whole)
    labels = chart_labels(new_faces, new_vertices.shape[0])
    positive = np.bincount(labels, weights=signed > 0, minlength=labels.max() + 1)
    count = np.bincount(labels, minlength=labels.max() + 1)
    assert ((positive == 0) | (positive == count)).all()
    # charts in two groups: each group's texels are apart from the other's (no overlap, and a gutter between)
    group = np.unique(labels, return_inverse=True)[1] % 2
    normals = np.zeros_like(new_vertices)
    coverage = []
    for half in range(2):
        with torch.no_grad():
            face = ops.rasterize_uv_atlas(torch.as_tensor(new_vertices), torch.as_tensor(new_faces[group == half]),
                                          torch.as_tensor(normals), torch.as_tensor(uvs), size=size)[0]
        coverage.append(face.numpy() >= 0)
    # the covered texel centres add up to the charts' area (overlapping charts would cover less than their sum)
    covered = (coverage[0] | coverage[1]).sum() / size**2
    assert abs(covered - area) < 0.05 * area
    import cv2

    gap = texture.GUTTER_TEXELS // 2 - 1  # texels: charts are at least twice this plus one apart
    grown = cv2.dilate(coverage[0].astype(np.uint8), np.ones((2 * gap + 1, 2 * gap + 1), np.uint8)) > 0
    assert not (grown & coverage[1]).any()


def test_unwrap_rejects_bad_input(sphere):
    vertices, faces = sphere
    with pytest.raises(ValueError, match="faces index vertices"):
        texture.unwrap(vertices, faces + vertices.shape[0])
    with pytest.raises(ValueError, match=r"vertices must have shape \[N,3\]"):
        texture.unwrap(vertices[:, :2], faces)
    with pytest.raises(ValueError, match="gutter"):
        texture.unwrap(vertices, faces, gutter=0)


# ---------------------------------------------------------------------------------------------------------
# bakes of an analytic striped sphere
# ---------------------------------------------------------------------------------------------------------

STRIPES = 6
PALETTE = np.array([[0.9, 0.2, 0.2], [0.2, 0.8, 0.3], [0.2, 0.3, 0.9], [0.9, 0.8, 0.2], [0.8, 0.3, 0.8],
                    [0.3, 0.8, 0.8]])


def striped_color(points: np.ndarray) -> np.ndarray:
    """[N,3] colour of sphere points: a hue per longitude stripe, darker on the lower hemisphere."""
    longitude = np.arctan2(points[:, 1], points[:, 0]) % (2 * math.pi)
    stripe = np.minimum((longitude / (2 * math.pi) * STRIPES).astype(int), STRIPES - 1)
    return PALETTE[stripe] * np.where(points[:, 2] >= 0, 1.0, 0.55)[:, None]


def distance_to_stripe_edges(points: np.ndarray) -> np.ndarray:
    """[N] distance [m] (about) from each sphere point to the nearest colour edge."""
    radius = np.linalg.norm(points[:, :2], axis=1)
    longitude = np.arctan2(points[:, 1], points[:, 0]) % (2 * math.pi)
    width = 2 * math.pi / STRIPES
    to_edge = np.minimum(longitude % width, width - longitude % width) * radius
    return np.minimum(to_edge, np.abs(points[:, 2]))


def sphere_view(K: np.ndarray, world_to_camera: np.ndarray, size: int, radius: float):
    """(colour [S,S,3], alpha [S,S], depth [S,S]) of the striped sphere of ``radius`` at the origin, ray-cast
    through each pixel's centre."""
    rows, columns = np.mgrid[0:size, 0:size].astype(np.float64)
    rays = np.stack([(columns - K[0, 2]) / K[0, 0], (rows - K[1, 2]) / K[1, 1], np.ones_like(rows)], axis=-1)
    rotation, translation = world_to_camera[:3, :3], world_to_camera[:3, 3]
    centre = -rotation.T @ translation
    directions = rays @ rotation  # camera -> world: R^T d for each ray
    # |centre + s d|^2 = r^2, s along the ray scaled so that camera z = s
    a = (directions**2).sum(-1)
    b = 2.0 * directions @ centre
    c = centre @ centre - radius**2
    disc = b * b - 4 * a * c
    hit = disc > 0
    s = np.where(hit, (-b - np.sqrt(np.maximum(disc, 0.0))) / (2 * a), np.inf)
    points = centre + s[..., None] * directions
    color = np.where(hit[..., None], striped_color(points.reshape(-1, 3)).reshape(size, size, 3), 0.0)
    return color.astype(np.float32), hit.astype(np.float32), np.where(hit, s, np.inf).astype(np.float32)


def striped_views(count: int, size: int, *, up_only: bool = False) -> list[CanonicalView]:
    cameras = view_cameras(np.full(3, -0.5), np.full(3, 0.5), np.array([0.0, 0.0, 1.0]), count=count, size=size)
    views = []
    for K, matrix in cameras:
        if up_only and (-matrix[:3, :3].T @ matrix[:3, 3])[2] < 0.3:
            continue
        color, alpha, depth = sphere_view(K, matrix, size, 0.5)
        views.append(CanonicalView(K.astype(np.float32), matrix.astype(np.float32), size, size, color, alpha, depth))
    return views


@pytest.fixture(scope="module")
def views():
    return striped_views(24, 128)


def sample_texture(atlas: np.ndarray, uvs: np.ndarray) -> np.ndarray:
    """[N,3] bilinear samples [0..255] of an atlas at UVs (texel centres at (c + 0.5) / S)."""
    size = atlas.shape[0]
    x, y = uvs[:, 0] * size - 0.5, uvs[:, 1] * size - 0.5
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    at = lambda r, c: atlas[np.clip(r, 0, size - 1), np.clip(c, 0, size - 1)].astype(np.float64)
    top = at(y0, x0) * (1 - fx) + at(y0, x0 + 1) * fx
    bottom = at(y0 + 1, x0) * (1 - fx) + at(y0 + 1, x0 + 1) * fx
    return top * (1 - fy) + bottom * fy


def test_bake_texture_reproduces_the_striped_sphere(sphere, unwrapped, views):
    new_vertices, new_faces, uvs, source_vertex = unwrapped
    normals = new_vertices / np.linalg.norm(new_vertices, axis=1, keepdims=True)
    atlas = texture.bake_texture(new_vertices, new_faces, normals, uvs, views, size=256, device="cpu")
    assert atlas.shape == (256, 256, 3) and atlas.dtype == np.uint8
    expected = striped_color(new_vertices) * 255.0
    away = distance_to_stripe_edges(new_vertices) > 0.04
    assert away.mean() > 0.5
    error = np.abs(sample_texture(atlas, uvs) - expected)[away]
    assert np.percentile(error, 99) <= 2.0 and error.max() <= 6.0
    # texel centres inside the charts, away from the edges, too
    with torch.no_grad():
        face, _, point, _, _ = ops.rasterize_uv_atlas(torch.as_tensor(new_vertices), torch.as_tensor(new_faces),
                                                      torch.as_tensor(normals), torch.as_tensor(uvs), size=256)
    covered = face.numpy() >= 0
    points = point.numpy()[covered]
    inner = distance_to_stripe_edges(points) > 0.03
    texel_error = np.abs(atlas[covered].astype(np.float64) - striped_color(points) * 255.0)[inner]
    assert np.percentile(texel_error, 99) <= 4.0
    # the gutter holds chart colours: no black texel anywhere, least of all beside a chart
    assert (atlas.max(axis=2) > 20).all()


def test_vertex_colors_reproduce_the_striped_sphere(sphere, views):
    vertices, faces = sphere
    normals = vertices / np.linalg.norm(vertices, axis=1, keepdims=True)
    colors = texture.vertex_colors(vertices, normals, views, device="cpu")
    assert colors.shape == vertices.shape and colors.dtype == np.uint8
    away = distance_to_stripe_edges(vertices) > 0.04
    error = np.abs(colors.astype(np.float64) - striped_color(vertices) * 255.0)[away]
    assert np.percentile(error, 99) <= 2.0 and error.max() <= 6.0


def test_points_no_view_sees_take_the_nearest_seen_colour(sphere, unwrapped):
    # cameras above the sphere only: its lower cap is seen by none and takes the colours of the seen band's
    vertices, faces = sphere
    views = striped_views(24, 96, up_only=True)
    normals = vertices / np.linalg.norm(vertices, axis=1, keepdims=True)
    colors = texture.vertex_colors(vertices, normals, views, device="cpu").astype(np.float64)
    cap = vertices[:, 2] < -0.45
    assert cap.sum() > 10
    dark = PALETTE * 0.55 * 255.0
    distance = np.abs(colors[cap][:, None] - dark[None]).max(axis=2).min(axis=1)
    assert np.percentile(distance, 90) <= 6.0  # each an (unmixed) stripe colour of the lower hemisphere
    new_vertices, new_faces, uvs, _ = unwrapped
    new_normals = new_vertices / np.linalg.norm(new_vertices, axis=1, keepdims=True)
    atlas = texture.bake_texture(new_vertices, new_faces, new_normals, uvs, views, size=128, device="cpu")
    assert (atlas.max(axis=2) > 20).all()


def test_bake_texture_rejects_bad_input(unwrapped, views):
    new_vertices, new_faces, uvs, _ = unwrapped
    normals = new_vertices
    with pytest.raises(ValueError, match="uvs has"):
        texture.bake_texture(new_vertices, new_faces, normals, uvs[:-1], views, size=64)
    with pytest.raises(ValueError, match="size"):
        texture.bake_texture(new_vertices, new_faces, normals, uvs, views, size=0)
    broken = CanonicalView(views[0].K, views[0].world_to_camera, 128, 128, views[0].color[:10], views[0].alpha,
                           views[0].depth)
    with pytest.raises(ValueError, match="view 0"):
        texture.vertex_colors(new_vertices, normals, [broken])
