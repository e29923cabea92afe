"""The avatar as a textured, skinned triangle mesh for engines and DCC tools (``warpavatar-export``).

Stages, each a module: :mod:`~warpavatar.mesh.views` (renders of the canonical avatar all around it),
:mod:`~warpavatar.mesh.surface` (a closed surface fused from them, floaters dropped, decimated),
:mod:`~warpavatar.mesh.texture` (UVs and a texture atlas baked from the renders, vertex colours),
:mod:`~warpavatar.mesh.skin` (skin weights from the voxel skinning field, the motion as skinning transforms
plus per-frame offsets where parts move the avatar beyond skinning). The data between them is in
:mod:`~warpavatar.mesh.mesh_data`.
"""

from warpavatar.mesh.mesh_data import AvatarMesh, CanonicalView, MeshAnimation

__all__ = ["AvatarMesh", "CanonicalView", "MeshAnimation"]
