"""TSDF kernels: depth and colour images of an object fused into a truncated signed distance on a voxel grid.

Each voxel centre is projected into every view (a pinhole camera, OpenCV's convention) and read at its nearest
pixel. Where a view sees background there (alpha below a threshold, or no finite depth), the voxel lies in front
of nothing along that pixel's ray: it is carved as empty and no other view is read (space carving; what is left is
inside every silhouette, so an object seen all around comes out closed). Otherwise the view's signed distance
along its ray, ``depth - z`` (positive in front of the surface), counts if it is no less than ``-truncation``
(further behind the surface is occluded: the view says nothing there), clamped to ``+truncation``; the
voxel's value is the mean over the views that count, and its colour the mean of theirs (un-premultiplied by
alpha). A voxel inside every silhouette that it falls into but occluded in all of them is inside the object
(``-truncation``); one that falls into no image at all is unknown and written as empty (``+truncation``).

Voxel ``(i, j, k)`` of a ``[X, Y, Z]`` grid has its centre at ``origin + voxel_size * (i, j, k)`` and flat index
``(i * Y + j) * Z + k``. No gradients (``enable_backward=False``): the surface is extracted once, for export.
Launchers take Warp arrays, check their sizes and skip empty work; the torch bridge is :mod:`warpavatar._src.tsdf`.
"""

from __future__ import annotations

import warp as wp

from warpavatar.kernels.launch import launch

__all__ = ["integrate_tsdf"]


@wp.kernel(enable_backward=False)
def integrate_tsdf_kernel(depth: wp.array3d(dtype=wp.float32), alpha: wp.array3d(dtype=wp.float32),
                          color: wp.array3d(dtype=wp.vec3), intrinsics: wp.array(dtype=wp.mat33),
                          world_to_camera: wp.array(dtype=wp.mat44), origin: wp.vec3, voxel_size: wp.float32,
                          size_y: wp.int32, size_z: wp.int32, truncation: wp.float32, alpha_threshold: wp.float32,
                          tsdf: wp.array(dtype=wp.float32), weight: wp.array(dtype=wp.float32),
                          voxel_color: wp.array(dtype=wp.vec3)):
    """One thread per voxel: its signed distance, the number of views averaged and its mean colour."""
    index = wp.tid()
    k = index % size_z
    j = (index // size_z) % size_y
    i = index // (size_z * size_y)
    px = origin[0] + voxel_size * wp.float32(i)
    py = origin[1] + voxel_size * wp.float32(j)
    pz = origin[2] + voxel_size * wp.float32(k)
    view_count = depth.shape[0]
    height = depth.shape[1]
    width = depth.shape[2]
    right = wp.float32(width) - 0.5
    bottom = wp.float32(height) - 0.5
    total = wp.float32(0.0)
    count = wp.float32(0.0)
    rgb = wp.vec3(0.0, 0.0, 0.0)
    seen = int(0)
    carved = int(0)
    for view in range(view_count):
        m = world_to_camera[view]
        x = m[0, 0] * px + m[0, 1] * py + m[0, 2] * pz + m[0, 3]
        y = m[1, 0] * px + m[1, 1] * py + m[1, 2] * pz + m[1, 3]
        z = m[2, 0] * px + m[2, 1] * py + m[2, 2] * pz + m[2, 3]
        if z > 0.0:
            K = intrinsics[view]
            xn = x / z
            yn = y / z
            u = K[0, 0] * xn + K[0, 1] * yn + K[0, 2]
            v = K[1, 1] * yn + K[1, 2]
            if u >= -0.5 and u < right and v >= -0.5 and v < bottom:
                column = wp.min(wp.int32(wp.floor(u + 0.5)), width - 1)
                row = wp.min(wp.int32(wp.floor(v + 0.5)), height - 1)
                seen = 1
                a = alpha[view, row, column]
                d = depth[view, row, column]
                if a < alpha_threshold or not wp.isfinite(d):
                    carved = 1
                    break
                distance = d - z
                if distance >= -truncation:
                    total += wp.min(distance, truncation)
                    count += 1.0
                    rgb += color[view, row, column] / wp.max(a, 1.0e-6)
    if carved == 1 or seen == 0:
        tsdf[index] = truncation
        weight[index] = 0.0
        voxel_color[index] = wp.vec3(0.0, 0.0, 0.0)
    elif count > 0.0:
        tsdf[index] = total / count
        weight[index] = count
        voxel_color[index] = rgb / count
    else:
        tsdf[index] = -truncation
        weight[index] = 0.0
        voxel_color[index] = wp.vec3(0.0, 0.0, 0.0)


def integrate_tsdf(depth: wp.array, alpha: wp.array, color: wp.array, intrinsics: wp.array,
                   world_to_camera: wp.array, origin, voxel_size: float, grid_shape: tuple[int, int, int],
                   truncation: float, alpha_threshold: float, tsdf: wp.array, weight: wp.array,
                   voxel_color: wp.array) -> None:
    """Fuse ``V`` views into a voxel grid (launcher of :func:`integrate_tsdf_kernel`; see the module doc).

    Args:
        depth: [V,H,W] float32 camera-space z of each pixel [m] (``inf`` or NaN where there is none).
        alpha: [V,H,W] float32 coverage in 0..1.
        color: [V,H,W] vec3 RGB premultiplied by alpha.
        intrinsics: [V] mat33 pinhole intrinsics [px] (row 2 is not read: ``(0, 0, 1)``).
        world_to_camera: [V] mat44 rigid extrinsics (OpenCV: z forward).
        origin: (x, y, z) centre of voxel (0, 0, 0) [m].
        voxel_size: spacing of the voxel centres [m], > 0.
        grid_shape: ``(X, Y, Z)`` voxels along x, y, z.
        truncation: largest magnitude of the signed distance [m], > 0.
        alpha_threshold: a pixel with less alpha is background.
        tsdf, weight: [X*Y*Z] float32 outputs: the signed distance [m] in ``-truncation..truncation`` and the
            number of views averaged (0 for carved, unknown and occluded voxels).
        voxel_color: [X*Y*Z] vec3 output: the views' mean colour (0 where ``weight`` is 0).
    """
    view_count, height, width = depth.shape
    for name, array in (("alpha", alpha), ("color", color)):
        if tuple(array.shape) != (view_count, height, width):
            raise ValueError(f"{name} has shape {tuple(array.shape)}, depth {(view_count, height, width)}")
    for name, array in (("intrinsics", intrinsics), ("world_to_camera", world_to_camera)):
        if array.shape[0] != view_count:
            raise ValueError(f"{name} has {array.shape[0]} views, depth {view_count}")
    size_x, size_y, size_z = (int(extent) for extent in grid_shape)
    voxel_count = size_x * size_y * size_z
    for name, array in (("tsdf", tsdf), ("weight", weight), ("voxel_color", voxel_color)):
        if array.shape[0] != voxel_count:
            raise ValueError(f"{name} has {array.shape[0]} voxels, the grid {voxel_count}")
    if not (voxel_size > 0.0 and truncation > 0.0):
        raise ValueError(f"voxel_size and truncation must be positive, got {voxel_size} and {truncation}")
    if voxel_count == 0:
        return
    launch(integrate_tsdf_kernel, dim=voxel_count, device=tsdf.device,
           inputs=[depth, alpha, color, intrinsics, world_to_camera, wp.vec3(*(float(c) for c in origin)),
                   float(voxel_size), size_y, size_z, float(truncation), float(alpha_threshold)],
           outputs=[tsdf, weight, voxel_color])
