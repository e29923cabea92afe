"""Physics the avatar's parts use: a mass-spring cloth on a garment's node graph, collision capsules fitted to
the body's own Gaussians, and the rotations of the nodes' neighbourhoods that garment Gaussians ride on.

Built on :mod:`warpavatar.ops` (Warp kernels) and :mod:`warpavatar.geometry` only; nothing here knows the avatar
model, the extensions or the fit.
"""

from warpavatar.sim.cloth import Capsules, ClothGraph, ClothModel, ClothState, cloth_graph

__all__ = ["Capsules", "ClothGraph", "ClothModel", "ClothState", "cloth_graph"]
