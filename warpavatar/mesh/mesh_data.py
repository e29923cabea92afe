"""The data the mesh export passes between its stages: views of the canonical avatar, the mesh, its animation.

Data flows one way: avatar -> :class:`CanonicalView` renders -> surface (``warpavatar.mesh.surface``) ->
UVs and texture (``warpavatar.mesh.texture``) -> skin weights and animation (``warpavatar.mesh.skin``) ->
a file (``warpavatar.io.gltf``, ``warpavatar.io.usd_mesh``, static ``.obj`` / ``.ply`` through trimesh).

Units are metres, cameras are OpenCV's (x right, y down, z forward; ``K`` with pixel centres at integers), 4x4
matrices act on column vectors, and every array is numpy (float32 unless said).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["CanonicalView", "AvatarMesh", "MeshAnimation"]


@dataclass
class CanonicalView:
    """One render of the avatar in its canonical (rest) pose.

    Attributes:
        K: [3,3] pinhole intrinsics [px].
        world_to_camera: [4,4] rigid OpenCV-convention extrinsic.
        width, height: image size [px].
        color: [H,W,3] RGB in 0..1 on black (premultiplied by alpha: the rasterizer's image).
        alpha: [H,W] coverage in 0..1.
        depth: [H,W] expected camera-space z [m] (the rasterizer's depth divided by alpha), ``inf`` where alpha
            is below half.
    """

    K: np.ndarray
    world_to_camera: np.ndarray
    width: int
    height: int
    color: np.ndarray
    alpha: np.ndarray
    depth: np.ndarray


@dataclass
class AvatarMesh:
    """The avatar's surface in the canonical pose, with what an engine needs to texture and skin it.

    Attributes:
        vertices: [V,3] canonical positions [m].
        faces: [F,3] int32 vertex indices, counter-clockwise seen from outside (normals point out).
        normals: [V,3] unit vertex normals.
        uvs: [V,2] texture coordinates in 0..1, glTF's convention (u right, v down from the image's top row);
            None before unwrapping. Vertices are split along UV seams, so V counts the split ones.
        texture: [S,S,3] uint8 RGB atlas, row 0 at the top; None before baking.
        vertex_colors: [V,3] uint8 RGB; None before baking.
        joint_indices: [V,4] int32 joints of ``joint_names`` (the rig with its grown joints); None before skinning.
        joint_weights: [V,4] float32, each row summing to 1, largest first; None before skinning.
        joint_names, joint_parents, joint_heads: the rig: names (J+E), parents [J+E] int32 (-1 for a root),
            rest pivots [J+E,3] [m] (rest joint frames are unrotated, at their heads); None before skinning.
        up: [3] the world's up direction of the avatar's skeleton.
    """

    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray
    uvs: np.ndarray | None = None
    texture: np.ndarray | None = None
    vertex_colors: np.ndarray | None = None
    joint_indices: np.ndarray | None = None
    joint_weights: np.ndarray | None = None
    joint_names: list[str] | None = None
    joint_parents: np.ndarray | None = None
    joint_heads: np.ndarray | None = None
    up: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0], dtype=np.float32))

    @property
    def vertex_count(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def face_count(self) -> int:
        return int(self.faces.shape[0])


@dataclass
class MeshAnimation:
    """A motion of the mesh, as an engine plays it: skinning transforms per frame, plus what skinning alone
    cannot move (cloth, secondary motion) as per-frame offsets of the rest vertices, applied before skinning.

    Attributes:
        joint_transforms: [T,J+E,4,4] skinning transforms (rest pose -> posed world) of the rig's joints.
        frame_ids: [T] int64 frame ids of the motion's own clock.
        fps: frames per second of the frame ids.
        vertex_offsets: [T,V,3] float32 offsets [m] added to the rest vertices before skinning (glTF morph
            targets and UsdSkel time-sampled points both apply before skinning), or None where skinning
            reproduces the avatar within :data:`warpavatar.mesh.skin.OFFSET_TOLERANCE`.
    """

    joint_transforms: np.ndarray
    frame_ids: np.ndarray
    fps: float
    vertex_offsets: np.ndarray | None = None

    @property
    def frame_count(self) -> int:
        return int(self.joint_transforms.shape[0])
