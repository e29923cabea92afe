"""The ray-cast mesh renderer (ops.render_mesh) against its brute-force torch reference, per device, and against
images and depths known in closed form: a textured quad shows its texels, a plane its analytic depth."""

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from warpavatar import _torch_impl, ops


def look_at(eye, target, up=(0.0, -1.0, 0.0)) -> torch.Tensor:
    """[4,4] OpenCV world_to_camera of a camera at ``eye`` looking at ``target`` (image up along ``up``)."""
    eye, target, up = (torch.as_tensor(v, dtype=torch.float64) for v in (eye, target, up))
    forward = (target - eye) / (target - eye).norm()
    right = torch.linalg.cross(forward, up)
    right = right / right.norm()
    down = torch.linalg.cross(forward, right)
    rotation = torch.stack([right, down, forward])
    matrix = torch.eye(4, dtype=torch.float64)
    matrix[:3, :3] = rotation
    matrix[:3, 3] = -rotation @ eye
    return matrix


def random_scene(seed: int, *, width: int, height: int, face_count: int):
    """Random triangles around the origin seen by a random camera, with uvs, a texture and vertex colours."""
    generator = torch.Generator().manual_seed(seed)
    centres = torch.randn(face_count, 1, 3, generator=generator, dtype=torch.float64) * 0.4
    vertices = (centres + 0.25 * torch.randn(face_count, 3, 3, generator=generator, dtype=torch.float64))
    vertices = vertices.reshape(-1, 3)
    faces = torch.arange(face_count * 3).reshape(face_count, 3)
    direction = torch.randn(3, generator=generator, dtype=torch.float64)
    eye = 3.0 * direction / direction.norm()
    focal = 0.9 * width + 10.0 * float(torch.rand(1, generator=generator))
    K = torch.tensor([[focal, 0.0, (width - 1) / 2 + 0.7], [0.0, focal * 1.1, (height - 1) / 2 - 0.4], [0, 0, 1]],
                     dtype=torch.float64)
    return {
        "vertices": vertices.float(), "faces": faces, "K": K, "world_to_camera": look_at(eye, (0.0, 0.0, 0.0)),
        "uvs": torch.rand(vertices.shape[0], 2, generator=generator) * 1.2 - 0.1,  # a little past the edges
        "texture": (torch.rand(7, 5, 3, generator=generator) * 255).to(torch.uint8),
        "vertex_colors": torch.rand(vertices.shape[0], 3, generator=generator),
        "background": torch.rand(3, generator=generator),
    }


@pytest.mark.parametrize("seed, shading", [(0, "texture"), (1, "vertex_colors"), (2, "constant"), (3, "texture")])
def test_matches_reference(device, seed, shading):
    width, height = 40, 32
    scene = random_scene(seed, width=width, height=height, face_count=40)
    options = {"background": scene["background"].to(device)}
    if shading == "texture":
        options.update(uvs=scene["uvs"].to(device), texture=scene["texture"].to(device))
    elif shading == "vertex_colors":
        options.update(vertex_colors=scene["vertex_colors"].to(device))
    arguments = (scene["vertices"].to(device), scene["faces"].to(device), scene["K"], scene["world_to_camera"],
                 width, height)
    image, alpha, depth = ops.render_mesh(*arguments, **options)
    ref_image, ref_alpha, ref_depth = _torch_impl.render_mesh(*arguments, **options)
    for value in (image, alpha, depth):
        assert value.device.type == torch.device(device).type and value.dtype == torch.float32
    assert image.shape == (height, width, 3) and alpha.shape == depth.shape == (height, width)
    covered = float(ref_alpha.mean())
    assert 0.2 < covered < 0.95  # the scene fills part of the frame, so hits and misses are both tested
    # a ray through a shared edge or an exact depth tie may pick either face: a pixel or two can differ
    agree = (alpha == ref_alpha) & ((depth - ref_depth).abs() < 1e-4)
    assert int((~agree).sum()) <= 2
    torch.testing.assert_close(image[agree], ref_image[agree], atol=2e-4, rtol=0)
    torch.testing.assert_close(depth[agree], ref_depth[agree], atol=1e-4, rtol=1e-5)
    assert torch.equal(image[alpha == 0], scene["background"].to(device).expand(int((alpha == 0).sum()), 3))
    assert bool((depth[alpha == 0] == 0).all()) and bool((depth[alpha == 1] > 0).all())


def quad_facing_camera(width: int, height: int, *, focal: float, depth: float):
    """A quad at camera depth ``depth`` whose edges lie on the image's outer pixel edges (camera at the origin,
    looking along +z), with glTF uvs: (0, 0) at the image's top-left corner, v growing downwards."""
    cx, cy = (width - 1) / 2, (height - 1) / 2
    left, right = (-0.5 - cx) * depth / focal, (width - 0.5 - cx) * depth / focal
    top, bottom = (-0.5 - cy) * depth / focal, (height - 0.5 - cy) * depth / focal
    vertices = torch.tensor([[left, top, depth], [right, top, depth], [right, bottom, depth], [left, bottom, depth]])
    uvs = torch.tensor([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    K = torch.tensor([[focal, 0.0, cx], [0.0, focal, cy], [0.0, 0.0, 1.0]])
    return vertices, faces, uvs, K


def test_a_textured_quad_shows_its_texels(device):
    width, height = 6, 4
    vertices, faces, uvs, K = quad_facing_camera(width, height, focal=5.0, depth=2.0)
    texture = torch.randint(0, 256, (height, width, 3), generator=torch.Generator().manual_seed(3), dtype=torch.uint8)
    image, alpha, _ = ops.render_mesh(vertices.to(device), faces, K, torch.eye(4), width, height, uvs=uvs,
                                      texture=texture.numpy())
    # pixel (column i, row j) sees uv ((i + 0.5) / W, (j + 0.5) / H): the centre of texel (row j, column i)
    torch.testing.assert_close(image.cpu(), texture.float() / 255, atol=1e-5, rtol=0)
    assert bool((alpha == 1).all())


def test_a_coarse_texture_is_interpolated_bilinearly_and_clamped(device):
    width, height = 8, 6
    vertices, faces, uvs, K = quad_facing_camera(width, height, focal=5.0, depth=1.5)
    texture = torch.rand(3, 4, 3, generator=torch.Generator().manual_seed(4))
    image, _, _ = ops.render_mesh(vertices.to(device), faces, K, torch.eye(4), width, height, uvs=uvs,
                                  texture=texture)
    # a 2x upsampling with half-pixel centres and clamped borders: texel centres at (c + 0.5) / S
    expected = F.interpolate(texture.permute(2, 0, 1)[None], size=(height, width), mode="bilinear",
                             align_corners=False)[0].permute(1, 2, 0)
    torch.testing.assert_close(image.cpu(), expected, atol=1e-5, rtol=0)


def test_depth_is_the_analytic_depth_of_a_plane(device):
    width, height = 48, 36
    normal = torch.tensor([0.3, -0.2, 1.0], dtype=torch.float64)
    normal = normal / normal.norm()
    offset = 0.25  # the plane n . x = offset
    # a large square in the plane, around the point of the plane nearest the origin
    centre = offset * normal
    side = torch.linalg.cross(normal, torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))
    side = side / side.norm()
    other = torch.linalg.cross(normal, side)
    corners = torch.stack([centre + 20 * (a * side + b * other) for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1))])
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    eye = torch.tensor([0.4, -0.3, 3.0], dtype=torch.float64)
    world_to_camera = look_at(eye, (0.1, 0.05, 0.0))
    K = torch.tensor([[40.0, 0.0, 23.2], [0.0, 42.0, 17.9], [0.0, 0.0, 1.0]], dtype=torch.float64)
    _, alpha, depth = ops.render_mesh(corners.float().to(device), faces, K, world_to_camera, width, height)
    rows, columns = torch.meshgrid(torch.arange(height, dtype=torch.float64),
                                   torch.arange(width, dtype=torch.float64), indexing="ij")
    rays = torch.stack([(columns - K[0, 2]) / K[0, 0], (rows - K[1, 2]) / K[1, 1], torch.ones_like(rows)], -1)
    world_rays = rays @ world_to_camera[:3, :3]  # camera-space z of each ray is 1, so t is the depth
    expected = (offset - normal @ eye) / (world_rays @ normal)
    assert bool((alpha == 1).all())
    torch.testing.assert_close(depth.cpu().double(), expected, rtol=1e-5, atol=1e-5)


def test_rays_that_miss_and_meshes_without_faces_show_the_background(device):
    background = torch.tensor([0.2, 0.4, 0.6])
    vertices = torch.tensor([[0.0, 0.0, -1.0], [1.0, 0.0, -1.0], [0.0, 1.0, -1.0]], device=device)  # behind
    K = torch.tensor([[10.0, 0.0, 4.5], [0.0, 10.0, 3.5], [0.0, 0.0, 1.0]])
    for faces in (torch.tensor([[0, 1, 2]]), np.zeros((0, 3), np.int32)):
        image, alpha, depth = ops.render_mesh(vertices, faces, K, torch.eye(4), 10, 8, background=background)
        assert torch.equal(image.cpu(), background.expand(8, 10, 3))
        assert not bool(alpha.any()) and not bool(depth.any())


def test_bad_inputs_are_named():
    vertices = torch.zeros(3, 3)
    K, pose = torch.eye(3), torch.eye(4)
    with pytest.raises(ValueError, match="uvs and texture"):
        ops.render_mesh(vertices, [[0, 1, 2]], K, pose, 4, 4, uvs=torch.zeros(3, 2))
    with pytest.raises(ValueError, match="faces index vertices 0..2"):
        ops.render_mesh(vertices, [[0, 1, 3]], K, pose, 4, 4)
    with pytest.raises(ValueError, match="uvs must have shape"):
        ops.render_mesh(vertices, [[0, 1, 2]], K, pose, 4, 4, uvs=torch.zeros(4, 2), texture=torch.zeros(2, 2, 3))
    with pytest.raises(ValueError, match="width must be a positive int"):
        ops.render_mesh(vertices, [[0, 1, 2]], K, pose, 0, 4)
    with pytest.raises(TypeError, match="faces must be an integer"):
        ops.render_mesh(vertices, torch.zeros(1, 3), K, pose, 4, 4)
    assert math.isclose(float(ops.render_mesh(vertices, [[0, 1, 2]], K, pose, 4, 4)[1].sum()), 0.0)
