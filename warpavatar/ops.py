"""The torch-facing API of warpavatar's Warp kernels.

Every function here takes and returns torch tensors on CPU or CUDA, runs hand-written Warp kernels on
torch's current stream and is differentiable through ``torch.autograd`` (backward passes are explicit
kernels). A plain-torch reference of each, with the same signature, is in :mod:`warpavatar._torch_impl`.
The exceptions are :func:`apply_correction`, :func:`match_frame_code` and :func:`frame_bias`, playback's
few-kernel forms of the pose correction's torch code (:func:`warpavatar.extensions.pose_correction.corrected_gaussians`,
``PoseCorrection.frame_code`` and the first layer's bias in ``PoseCorrection._outputs``, their references),
without gradients, and :func:`integrate_tsdf`, the mesh export's fusion of canonical renders into a voxel grid
(no gradients), and :func:`render_mesh`, a ray-cast triangle-mesh renderer that measures an exported mesh against
the Gaussians (no gradients either), and :func:`closest_triangles`, which binds Gaussians to a mesh (no gradients),
and the texture bake's :func:`rasterize_uv_atlas`, :func:`average_view_colors` and :func:`nearest_points` (an
export step: no gradients).
Conventions: quaternions are (w, x, y, z); cameras follow OpenCV (x right, y down, z forward,
``world_to_camera`` 4x4, intrinsics ``K`` 3x3 with pixel centres at integer coordinates as
``docs/conventions.md`` states); lengths are in world units (metres in the supplied data).
"""

from warpavatar._src.cloth import cloth_edge_terms
from warpavatar._src.collision import push_out_of_capsules
from warpavatar._src.correction import apply_correction, frame_bias, match_frame_code
from warpavatar._src.knn import knn_graph
from warpavatar._src.mesh_render import render_mesh
from warpavatar._src.poses import corrected_poses, pose_priors
from warpavatar._src.shading import view_colors
from warpavatar._src.sheet_cloth import sheet_forces, sheet_rollout
from warpavatar._src.skinning import inverse_lbs, lbs, sample_grid
from warpavatar._src.splat import rasterize_gaussians, rasterizer_replays, rasterizer_status
from warpavatar._src.springs import damping_loss, isometry_loss, spring_step
from warpavatar._src.texture_bake import average_view_colors, nearest_points, rasterize_uv_atlas
from warpavatar._src.triangle_binding import closest_triangles, pose_triangle_gaussians
from warpavatar._src.tsdf import integrate_tsdf

__all__ = [
    "rasterize_gaussians",
    "rasterizer_status",
    "rasterizer_replays",
    "knn_graph",
    "spring_step",
    "isometry_loss",
    "damping_loss",
    "sample_grid",
    "lbs",
    "inverse_lbs",
    "push_out_of_capsules",
    "cloth_edge_terms",
    "sheet_forces",
    "sheet_rollout",
    "view_colors",
    "apply_correction",
    "match_frame_code",
    "frame_bias",
    "corrected_poses",
    "pose_priors",
    "integrate_tsdf",
    "render_mesh",
    "pose_triangle_gaussians",
    "closest_triangles",
    "rasterize_uv_atlas",
    "average_view_colors",
    "nearest_points",
]
