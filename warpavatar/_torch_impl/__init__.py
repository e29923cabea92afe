"""Plain-torch reference implementations of :mod:`warpavatar.ops`, same signatures, no Warp.

They are slow and simple on purpose: the tests compare the Warp kernels' values and gradients against them.
"""

from warpavatar._torch_impl.cloth import cloth_edge_terms
from warpavatar._torch_impl.collision import push_out_of_capsules
from warpavatar._torch_impl.correction import apply_correction, frame_bias, match_frame_code
from warpavatar._torch_impl.knn import knn_graph
from warpavatar._torch_impl.mesh_render import render_mesh
from warpavatar._torch_impl.poses import corrected_poses, pose_priors
from warpavatar._torch_impl.shading import view_colors
from warpavatar._torch_impl.sheet_cloth import sheet_forces, sheet_rollout
from warpavatar._torch_impl.skinning import inverse_lbs, lbs, sample_grid
from warpavatar._torch_impl.splat import rasterize_gaussians
from warpavatar._torch_impl.springs import damping_loss, isometry_loss, spring_step
from warpavatar._torch_impl.texture_bake import average_view_colors, nearest_points, rasterize_uv_atlas
from warpavatar._torch_impl.triangle_binding import closest_triangles, pose_triangle_gaussians
from warpavatar._torch_impl.tsdf import integrate_tsdf

# the same names as warpavatar.ops (tests/test_splat.py checks that the two lists agree)
__all__ = ["rasterize_gaussians", "knn_graph", "spring_step", "isometry_loss", "damping_loss", "sample_grid", "lbs",
           "inverse_lbs", "push_out_of_capsules",
           "cloth_edge_terms", "sheet_forces", "sheet_rollout", "view_colors", "apply_correction", "match_frame_code",
           "frame_bias",
           "corrected_poses", "pose_priors", "integrate_tsdf",
           "render_mesh", "pose_triangle_gaussians", "closest_triangles",
           "rasterize_uv_atlas", "average_view_colors", "nearest_points"]
