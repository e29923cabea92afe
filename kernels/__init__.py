"""Hand-written NVIDIA Warp kernels of warpavatar, grouped by family.

Installed as ``warpavatar.kernels``. Each family module holds its ``@wp.func`` helpers, its kernels and one
launcher per kernel; the launchers take and return ``warp.array`` objects and never touch torch. The
torch-facing, differentiable API is :mod:`warpavatar.ops`.

Families:
    splat: projection, tile binning and compositing of 3D Gaussians (forward and hand-written backward).
    knn: exact k-nearest-neighbour graph on a hash grid.
    springs: explicit-Euler mass-spring-damper step and its regularizers.
    skinning: trilinear sampling of a voxel field and linear blend skinning.
    collision: particles pushed out of capsules.
    cloth: a cloth substep's edge terms (length-spring rest offsets, edge damping).
    shading: view-dependent colour from spherical harmonics in each Gaussian's canonical frame.
    cloth_frame: a whole cloth substep fused in one kernel (rollouts without gradients).
    sheet_cloth: a triangle-mesh cloth: membrane, bending and drag forces, a substep, their backward.
    correction: a pose correction's outputs applied to canonical Gaussians in one pass (playback).
    poses: every frame's refined poses down the skeleton, and the priors of the refined motion (pose refinement).
    texture_bake: triangles rasterized into a UV atlas, points coloured from camera views, nearest points (mesh
        export).
    mesh_render: camera rays cast against a triangle mesh's BVH and the hits shaded (no gradients).
    triangle_binding: Gaussians bound to a triangle mesh posed from its vertices, and points' closest triangles.
    tsdf: views fused into a truncated signed distance on a voxel grid, with space carving (mesh export).

:mod:`~warpavatar.kernels.quaternion` holds the quaternion ``@wp.func`` helpers the families share, and
:mod:`~warpavatar.kernels.launch` the launch function every launcher calls (``wp.launch`` with the argument
packing done once per kernel).
"""
