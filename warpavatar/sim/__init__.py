"""Physics the avatar's parts use: a mass-spring cloth on a garment's node graph, a triangle-mesh cloth (a garment
sheet), collision capsules fitted to the body's own Gaussians, and the rotations of the nodes' neighbourhoods that garment Gaussians ride on.

Built on :mod:`warpavatar.ops` (Warp kernels) and :mod:`warpavatar.geometry` only; nothing here knows the avatar
model, the extensions or the fit.
"""

from warpavatar.sim.capsules import capsules_near, distance_to_segments, fit_body_capsules, pose_capsules
from warpavatar.sim.mass_spring_cloth import Capsules, ClothGraph, ClothModel, ClothState, cloth_graph
from warpavatar.sim.node_frames import nearest_nodes, node_rotations, ride_on_nodes
from warpavatar.sim.triangle_mesh_cloth import SheetCloth, SheetState, sheet_hinges

__all__ = ["Capsules", "ClothGraph", "ClothModel", "ClothState", "cloth_graph", "fit_body_capsules", "pose_capsules",
           "capsules_near",
           "distance_to_segments", "node_rotations", "nearest_nodes", "ride_on_nodes", "SheetCloth", "SheetState",
           "sheet_hinges"]
