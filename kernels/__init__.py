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
    correction: a pose correction's outputs applied to canonical Gaussians in one pass (playback).
    poses: every frame's refined poses down the skeleton, and the priors of the refined motion (pose refinement).

:mod:`~warpavatar.kernels.quaternion` holds the quaternion ``@wp.func`` helpers the families share, and
:mod:`~warpavatar.kernels.launch` the launch function every launcher calls (``wp.launch`` with the argument
packing done once per kernel).
"""
