"""Torch-facing mesh renderer (``kernels/mesh_render.py``): a posed triangle mesh seen through a pinhole camera.

One call builds Warp's BVH over the posed vertices (:class:`warp.Mesh`), casts one camera ray per pixel against
it and shades the hits from a texture, vertex colours or a constant; nothing is differentiable, and nothing is
read back to the host (faces given on the host are range-checked there; faces on CUDA are the caller's to get
right). The plain-torch reference with the same signature is
:func:`warpavatar._torch_impl.mesh_render.render_mesh`.
"""

from __future__ import annotations

import torch
import warp as wp

from warpavatar._src.warp_utils import check_tensor, to_warp, torch_stream_scope
from warpavatar.kernels import mesh_render as kernels

__all__ = ["render_mesh"]


def _float_tensor(name: str, value, device: torch.device, shape: tuple) -> torch.Tensor:
    tensor = torch.as_tensor(value)
    if tensor.is_complex() or tensor.dtype == torch.bool:
        raise TypeError(f"{name} must hold real numbers, got {tensor.dtype}")
    tensor = tensor.to(device=device, dtype=torch.float32)
    check_tensor(name, tensor, shape, dtype_kind="float32")
    return tensor.contiguous()


def _colors(name: str, value, device: torch.device, shape: tuple) -> torch.Tensor:
    """RGB in 0..1 as float32: uint8 values are divided by 255, floating-point ones used as given."""
    tensor = torch.as_tensor(value)
    scale = 1.0 / 255.0 if tensor.dtype == torch.uint8 else 1.0
    if not (tensor.is_floating_point() or tensor.dtype == torch.uint8):
        raise TypeError(f"{name} must be uint8 (0..255) or floating-point (0..1), got {tensor.dtype}")
    tensor = tensor.to(device=device, dtype=torch.float32) * scale
    check_tensor(name, tensor, shape, dtype_kind="float32")
    return tensor.contiguous()


def _mesh_inputs(vertices, faces, K, world_to_camera, width, height, uvs, texture, vertex_colors, background):
    """The inputs checked and converted (float32 on the vertices' device, faces int64); shared with the
    reference, so that both accept the same values."""
    check_tensor("vertices", vertices, (None, 3), dtype_kind="float")
    device = vertices.device
    vertex_count = vertices.shape[0]
    faces = torch.as_tensor(faces)
    check_tensor("faces", faces, (None, 3), dtype_kind="int")
    if faces.device.type == "cpu" and faces.numel() and (int(faces.min()) < 0 or int(faces.max()) >= vertex_count):
        raise ValueError(f"faces index vertices 0..{vertex_count - 1}, got indices {int(faces.min())}.."
                         f"{int(faces.max())}")
    faces = faces.to(device=device, dtype=torch.int64)
    for name, size in (("width", width), ("height", height)):
        if isinstance(size, bool) or not isinstance(size, int) or size < 1:
            raise ValueError(f"{name} must be a positive int, got {size!r}")
    K = _float_tensor("K", K, device, (3, 3))
    world_to_camera = _float_tensor("world_to_camera", world_to_camera, device, (4, 4))
    if (uvs is None) != (texture is None):
        raise ValueError("uvs and texture go together: give both or neither")
    if uvs is not None:
        uvs = _float_tensor("uvs", uvs, device, (vertex_count, 2))
        texture = _colors("texture", texture, device, (None, None, 3))
        if texture.shape[0] == 0 or texture.shape[1] == 0:
            raise ValueError(f"texture must hold at least one texel, got shape {list(texture.shape)}")
    if vertex_colors is not None:
        vertex_colors = _colors("vertex_colors", vertex_colors, device, (vertex_count, 3))
    background = (torch.zeros(3, dtype=torch.float32, device=device) if background is None
                  else _float_tensor("background", background, device, (3,)))
    return (vertices.detach().to(torch.float32).contiguous(), faces, K, world_to_camera, uvs, texture, vertex_colors,
            background)


def render_mesh(vertices: torch.Tensor, faces, K, world_to_camera, width: int, height: int, *, uvs=None,
                texture=None, vertex_colors=None, background=None
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Render a triangle mesh through an OpenCV pinhole camera by ray casting (the closest hit, either side of a
    face), without gradients.

    Pixel (column i, row j) is seen along the ray through its centre at integer coordinates
    (``docs/conventions.md``). A hit is shaded from ``texture`` at the interpolated ``uvs`` (bilinear, glTF
    convention: u right, v down from the top row, texel centres at ``(c + 0.5) / S``, clamped to the edge), else
    from the interpolated ``vertex_colors``, else white; colours are used as given (no colour-space conversion).

    Args:
        vertices: ``[V, 3]`` posed positions [world units], CPU or CUDA; the outputs are on its device.
        faces: ``[F, 3]`` integer vertex indices (a tensor or an array).
        K: ``[3, 3]`` intrinsics [px].
        world_to_camera: ``[4, 4]`` rigid extrinsic (OpenCV axes).
        width, height: image size [px].
        uvs: ``[V, 2]`` texture coordinates, with ``texture``.
        texture: ``[S_h, S_w, 3]`` RGB, row 0 at the top: uint8 (0..255) or floating-point (0..1).
        vertex_colors: ``[V, 3]`` RGB, uint8 or floating-point (used without a texture).
        background: ``[3]`` RGB where nothing is hit (default black).

    Returns:
        ``(image [H, W, 3], alpha [H, W], depth [H, W])`` float32: the shaded colour (the background where
        nothing is hit), 1 where a face is hit and 0 elsewhere, and the hit's camera-space z [world units] (0
        where nothing is hit, as the Gaussian rasterizer's alpha-weighted depth).
    """
    vertices, faces, K, world_to_camera, uvs, texture, vertex_colors, background = _mesh_inputs(
        vertices, faces, K, world_to_camera, width, height, uvs, texture, vertex_colors, background)
    device = vertices.device
    image = background.expand(height, width, 3).contiguous()
    alpha = torch.zeros((height, width), dtype=torch.float32, device=device)
    depth = torch.zeros((height, width), dtype=torch.float32, device=device)
    if faces.shape[0] == 0:
        return image, alpha, depth
    face_index = torch.empty((height, width), dtype=torch.int32, device=device)
    barycentrics = torch.empty((height, width, 2), dtype=torch.float32, device=device)
    faces32 = faces.to(torch.int32).contiguous()
    with torch_stream_scope(device):
        points = to_warp(vertices, dtype=wp.vec3)
        mesh = kernels.build_mesh(points, to_warp(faces32.reshape(-1)))
        kernels.cast_camera_rays(mesh, to_warp(K.reshape(1, 3, 3), dtype=wp.mat33),
                                 to_warp(world_to_camera.reshape(1, 4, 4), dtype=wp.mat44), to_warp(face_index),
                                 to_warp(barycentrics, dtype=wp.vec2), to_warp(depth))
        kernels.shade_mesh_hits(
            to_warp(face_index), to_warp(barycentrics, dtype=wp.vec2), to_warp(faces32),
            to_warp(background.reshape(1, 3), dtype=wp.vec3), to_warp(image, dtype=wp.vec3), to_warp(alpha),
            vertex_uvs=None if uvs is None else to_warp(uvs, dtype=wp.vec2),
            texture=None if texture is None else to_warp(texture, dtype=wp.vec3),
            vertex_colors=None if vertex_colors is None else to_warp(vertex_colors, dtype=wp.vec3))
        # freed here, on the stream the kernels were queued on (Warp frees device memory stream-ordered)
        del mesh
    return image, alpha, depth
