"""Skin weights of the avatar's mesh and its motion as an engine plays it: skinning transforms per frame, plus
offsets of the rest vertices where the avatar's parts move it beyond skinning.

Weights: each vertex reads the voxel skinning field
(:meth:`~warpavatar.model.skinning_field.VoxelSkinningField.weights`, trilinear interpolation of the weight grid
by :func:`warpavatar.ops.sample_grid`) at its canonical position and keeps its :data:`INFLUENCES` largest weights,
renormalised. With ``weights_from="gaussians"`` (what the export uses) a vertex instead blends the field's weights
at the centres of its :data:`WEIGHT_NEIGHBOURS` nearest Gaussians, each by its density there (opacity times the
Gaussian's falloff at the vertex): the field is fitted only where Gaussians are, and a fused surface lies outside
their centres (on the demo avatar, field weights read at the surface moved vertices a median 2 cm away from the
Gaussians around them), so the mesh then moves as the Gaussians it was made from. The joints are the rig's
(:meth:`Avatar.rig`: the skeleton's, then the joints its parts grow), in the order of :meth:`Avatar.pose_bones`'
transforms.

Offsets: parts such as secondary motion, dynamics, a simulated garment or the pose correction move Gaussians
away from where linear blend skinning (LBS) of their canonical centres puts them. Per frame, each Gaussian's
residual (its posed centre minus LBS of its stored canonical centre with the field's weights there) is carried to
the mesh's vertices by the same density shares as the weights (over the :data:`WEIGHT_NEIGHBOURS` nearest
Gaussians in the canonical pose: the Gaussians that make the surface there, not faint or distant ones that a part
moved far; on the robot benchmark subject, 1 % of the Gaussians carry residuals above 12 cm, and inverse-distance
shares over 8 gave the posed mesh spikes). Since LBS is linear in the rest position (``LBS(x + o) = LBS(x) + A o``,
with ``A`` the vertex's blended 3x3), the world residual ``r`` becomes the pre-skinning offset ``o = A^-1 r``, which
is what glTF morph targets and UsdSkel's time-sampled points both apply before skinning (damped where ``A`` nearly
collapses, in LBS's folds: see :func:`_blended_inverse`).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import torch

from warpavatar import ops
from warpavatar.mesh.mesh_data import AvatarMesh, MeshAnimation
from warpavatar.model.parts import AvatarPart

__all__ = ["INFLUENCES", "OFFSET_TOLERANCE", "WEIGHT_NEIGHBOURS", "top_influences", "skin_mesh",
           "gaussian_blended_weights", "mesh_animation", "lbs_vertices", "deforming_parts"]

INFLUENCES = 4
"""Joints per vertex (glTF's one JOINTS_0 / WEIGHTS_0 pair, most engines' default)."""

OFFSET_TOLERANCE = 1e-4
"""[m] The vertex offsets are dropped when the largest displacement they make in the posed world (the residual
carried to a vertex), over every vertex and frame, is below this: skinning alone reproduces the avatar."""

WEIGHT_NEIGHBOURS = 16
"""Nearest Gaussians (canonical pose) whose skin weights (with ``weights_from="gaussians"``) and residuals a vertex
blends, each by its density at the vertex."""

_OPACITY_FLOOR = 0.05  # Gaussians fainter than this (floaters, half-pruned ones) carry no residual to the mesh
_SINGULAR_FLOOR = 0.2  # singular values of a blended skinning 3x3 below this are damped when inverted
_CHUNK = 2048  # vertices per block of the nearest-Gaussian search (a [chunk, N] distance matrix)


def top_influences(weights: torch.Tensor | np.ndarray, *, count: int = INFLUENCES) -> tuple[np.ndarray, np.ndarray]:
    """The ``count`` largest weights of each row, renormalised to sum to 1, largest first.

    Rows with fewer than ``count`` joints are padded with joint 0 at weight 0. The largest weight of a row is set
    to one minus the others in float32, so each row sums to 1 to float32 rounding.

    Args:
        weights: [V,J] non-negative weights (each row with a positive sum).

    Returns:
        ``(joint_indices [V,count] int32, joint_weights [V,count] float32)``.
    """
    weights = torch.as_tensor(weights).detach().double().cpu()
    if weights.dim() != 2:
        raise ValueError(f"weights must have shape [V, J], got {list(weights.shape)}")
    keep = min(count, weights.shape[1])
    values, index = torch.topk(weights, keep, dim=1, largest=True, sorted=True)
    total = values.sum(1, keepdim=True)
    if bool((total <= 0).any()):
        raise ValueError("every vertex needs a positive skinning weight")
    values = (values / total).float().numpy()
    index = index.numpy().astype(np.int32)
    if keep < count:
        pad = count - keep
        values = np.concatenate([values, np.zeros((len(values), pad), np.float32)], axis=1)
        index = np.concatenate([index, np.zeros((len(index), pad), np.int32)], axis=1)
    index[values == 0] = 0  # an unused slot names joint 0 (as glTF asks)
    values[:, 0] = np.float32(1.0) - values[:, 1:].sum(1, dtype=np.float32)
    return index, values


def _density_neighbours(avatar, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Each of ``points`` [P,3]' :data:`WEIGHT_NEIGHBOURS` nearest Gaussians (canonical pose, those at least
    ``_OPACITY_FLOOR`` opaque): their indices [P,k] into the avatar's Gaussians and their shares [P,k] (rows sum to
    1), each Gaussian's density at the point, ``opacity * exp(-d^2 / 2)`` with ``d`` the point's Mahalanobis
    distance from it in units of its scales; a point that no neighbour reaches (every density below 1e-6) shares
    by inverse squared distance instead."""
    from warpavatar.geometry import quat_to_matrix

    gaussians = avatar.gaussians
    opacities = gaussians.opacities.detach().reshape(-1)
    solid = opacities >= _OPACITY_FLOOR
    if not bool(solid.any()):
        solid = torch.ones_like(solid)
    carriers = torch.nonzero(solid).squeeze(1)
    means = gaussians.means.detach()[carriers].contiguous()
    inverse_scales = 1.0 / gaussians.scales.detach()[carriers].clamp_min(1e-8)
    rotations = quat_to_matrix(gaussians.normalized_quats.detach()[carriers])  # [N,3,3], local -> canonical
    opacity = opacities[carriers]
    count = min(WEIGHT_NEIGHBOURS, means.shape[0])
    indices, shares = [], []
    for start in range(0, points.shape[0], _CHUNK):
        chunk = points[start:start + _CHUNK]
        distance, index = torch.topk(torch.cdist(chunk, means), count, dim=1, largest=False)
        offset = chunk[:, None, :] - means[index]  # [C,k,3]
        local = torch.einsum("ckji,ckj->cki", rotations[index], offset) * inverse_scales[index]
        density = opacity[index] * torch.exp(-0.5 * local.square().sum(-1))
        reached = density.max(1, keepdim=True).values > 1e-6
        share = torch.where(reached, density, 1.0 / (distance.square() + 1e-12))
        indices.append(carriers[index])
        shares.append(share / share.sum(1, keepdim=True))
    if not indices:
        empty = points.new_zeros((0, count))
        return empty.long(), empty
    return torch.cat(indices), torch.cat(shares)


def gaussian_blended_weights(avatar, points: torch.Tensor, grid: torch.Tensor | None = None) -> torch.Tensor:
    """[P,J+E] skin weights of canonical ``points`` [P,3] [m]: the field's weights at the centres of each point's
    nearest Gaussians, blended by each one's density at the point (:func:`_density_neighbours`). Rows sum to 1."""
    grid = avatar.field.grid_weights() if grid is None else grid
    index, share = _density_neighbours(avatar, points)
    weights = avatar.field.weights(avatar.gaussians.means.detach().contiguous(), grid)  # [N,J+E]
    return (share[:, :, None] * weights[index]).sum(1)


def skin_mesh(avatar, mesh: AvatarMesh, *, weights_from: str = "field") -> AvatarMesh:
    """The mesh with its skin weights and the avatar's rig (:attr:`AvatarMesh.joint_indices` and the rest).

    Args:
        avatar: the :class:`~warpavatar.model.Avatar`.
        mesh: the canonical mesh (its ``vertices`` in the avatar's canonical pose).
        weights_from: ``"field"``: the skinning field at each vertex; ``"gaussians"``: the field at the nearest
            Gaussians' centres, blended by their density at the vertex (:func:`gaussian_blended_weights`; for a
            surface made from the Gaussians).

    Returns:
        a copy of ``mesh`` with ``joint_indices`` / ``joint_weights`` (top :data:`INFLUENCES` of the skinning
        field at each vertex), ``joint_names`` / ``joint_parents`` / ``joint_heads`` (the skeleton with its grown
        joints) and ``up`` (the skeleton's).
    """
    if weights_from not in ("field", "gaussians"):
        raise ValueError(f"skin_mesh: weights_from must be 'field' or 'gaussians', got {weights_from!r}")
    device = avatar.gaussians.means.device
    rig = avatar.rig()
    with torch.no_grad():
        grid = avatar.field.grid_weights()
        points = torch.as_tensor(np.asarray(mesh.vertices), dtype=torch.float32, device=device).contiguous()
        if weights_from == "gaussians":  # once a position: vertices split along UV seams share one
            unique, inverse = torch.unique(points, dim=0, return_inverse=True)
            weights = gaussian_blended_weights(avatar, unique.contiguous(), grid)[inverse]
        else:
            weights = avatar.field.weights(points, grid)
    if weights.shape[1] != len(rig.names):
        raise ValueError(f"the skinning field has {weights.shape[1]} outputs but the rig {len(rig.names)} joints")
    joint_indices, joint_weights = top_influences(weights)
    return dataclasses.replace(
        mesh, joint_indices=joint_indices, joint_weights=joint_weights, joint_names=list(rig.names),
        joint_parents=np.asarray(rig.parents, dtype=np.int32), joint_heads=np.asarray(rig.heads, dtype=np.float32),
        up=np.asarray(rig.up, dtype=np.float32))


def deforming_parts(avatar) -> list[str]:
    """Names of the avatar's parts that move Gaussians beyond skinning (they override
    :meth:`~warpavatar.model.parts.AvatarPart.deform_canonical` or ``deform_posed``)."""
    return [name for name, part in avatar.parts.items()
            if type(part).deform_canonical is not AvatarPart.deform_canonical
            or type(part).deform_posed is not AvatarPart.deform_posed]


def _dense_weights(mesh: AvatarMesh, joint_count: int, device) -> torch.Tensor:
    if mesh.joint_indices is None or mesh.joint_weights is None:
        raise ValueError("the mesh has no skin weights (run skin_mesh first)")
    dense = torch.zeros(mesh.vertex_count, joint_count, dtype=torch.float32, device=device)
    index = torch.as_tensor(np.asarray(mesh.joint_indices), dtype=torch.long, device=device)
    if int(index.max()) >= joint_count or int(index.min()) < 0:
        raise ValueError(f"the mesh's joint indices must lie in 0..{joint_count - 1}")
    dense.scatter_add_(1, index, torch.as_tensor(np.asarray(mesh.joint_weights), dtype=torch.float32, device=device))
    return dense


def lbs_vertices(mesh: AvatarMesh, joint_transforms, offsets=None) -> np.ndarray:
    """The mesh's vertices posed by linear blend skinning with its top weights (:func:`warpavatar.ops.lbs`).

    Args:
        mesh: a skinned mesh (:func:`skin_mesh`).
        joint_transforms: [J+E,4,4] skinning transforms of the rig (rest pose -> posed world).
        offsets: [V,3] offsets [m] added to the rest vertices before skinning, or None.

    Returns:
        [V,3] float32 posed positions [m].
    """
    transforms = torch.as_tensor(np.asarray(joint_transforms), dtype=torch.float32)
    if transforms.dim() != 3 or transforms.shape[1:] != (4, 4):
        raise ValueError(f"joint_transforms must have shape [J, 4, 4], got {list(transforms.shape)}")
    rest = torch.as_tensor(np.asarray(mesh.vertices), dtype=torch.float32)
    if offsets is not None:
        rest = rest + torch.as_tensor(np.asarray(offsets), dtype=torch.float32)
    with torch.no_grad():
        posed, _ = ops.lbs(rest.contiguous(), _dense_weights(mesh, transforms.shape[0], "cpu"),
                           transforms.contiguous())
    return posed.numpy()


def _blended_inverse(mesh: AvatarMesh, transforms: torch.Tensor) -> torch.Tensor:
    """Inverse [V,3,3] (float64) of each vertex's blended skinning 3x3 for one frame's transforms [J+E,4,4].

    Where opposite rotations blend, the 3x3 nearly collapses (LBS's candy wrapper) and its exact inverse would
    turn a millimetre of residual into decimetres of offset. There, singular values ``s`` below
    :data:`_SINGULAR_FLOOR` are inverted as ``s / floor^2`` (damped: an offset is at most ``1 / floor`` times its
    residual), and the offset reproduces the residual only in part. A blend of rotations has no singular value
    above 1, so one whose determinant reaches the floor has none below it and is inverted exactly.
    """
    index = torch.as_tensor(np.asarray(mesh.joint_indices), dtype=torch.long, device=transforms.device)
    weights = torch.as_tensor(np.asarray(mesh.joint_weights), dtype=torch.float64, device=transforms.device)
    blended = (weights[:, :, None, None] * transforms[index][:, :, :3, :3].double()).sum(1)
    folded = torch.linalg.det(blended).abs() < _SINGULAR_FLOOR
    identity = torch.eye(3, dtype=blended.dtype, device=blended.device)
    inverse = torch.linalg.inv(torch.where(folded[:, None, None], identity, blended))
    if bool(folded.any()):
        fold = blended[folded]
        values, vectors = torch.linalg.eigh(fold.mT @ fold)  # squared singular values, right singular vectors
        damped = 1.0 / values.clamp_min(_SINGULAR_FLOOR ** 2)
        inverse[folded] = vectors @ torch.diag_embed(damped) @ vectors.mT @ fold.mT
    return inverse


def _motion_arrays(motion) -> tuple[np.ndarray, np.ndarray, float, float, dict[str, Any]]:
    bones = np.asarray(motion.bone_transforms, dtype=np.float32)
    if bones.ndim != 4 or bones.shape[2:] != (4, 4) or bones.shape[0] == 0:
        raise ValueError(f"the motion's bone transforms must have shape [T, J, 4, 4] with T >= 1, "
                         f"got {list(bones.shape)}")
    frame_ids = np.asarray(motion.frame_ids, dtype=np.int64).reshape(-1)
    if frame_ids.shape[0] != bones.shape[0]:
        raise ValueError(f"the motion has {bones.shape[0]} frames but {frame_ids.shape[0]} frame ids")
    return bones, frame_ids, float(motion.clock_fps), float(motion.fps), dict(motion.part_inputs or {})


def mesh_animation(avatar, mesh: AvatarMesh, motion, *, progress: bool = False) -> MeshAnimation:
    """The motion as skinning transforms of the mesh's rig, plus the offsets where parts move the avatar beyond
    skinning (see the module docstring).

    Args:
        avatar: the :class:`~warpavatar.model.Avatar` the mesh was made from.
        mesh: its skinned mesh (:func:`skin_mesh`).
        motion: a :class:`~warpavatar.io.exporters.ExportMotion` (``bone_transforms`` [T,J,4,4], ``frame_ids``,
            ``clock_fps`` for parts with state over time, ``fps`` the file declares, ``part_inputs``).
        progress: show a progress bar over the frames.

    Returns:
        a :class:`MeshAnimation` with ``joint_transforms`` [T,J+E,4,4], the motion's frame ids and declared fps,
        and ``vertex_offsets`` [T,V,3] or None (no part that deforms, or every displacement the offsets make
        below :data:`OFFSET_TOLERANCE`).
    """
    bones, frame_ids, clock_fps, fps, part_inputs = _motion_arrays(motion)
    device = avatar.gaussians.means.device
    joint_count = len(mesh.joint_names) if mesh.joint_names is not None else None
    if mesh.joint_indices is None or joint_count is None:
        raise ValueError("the mesh has no skin weights (run skin_mesh first)")
    frames = range(bones.shape[0])
    if progress:
        from tqdm import tqdm

        frames = tqdm(frames, desc="mesh animation", unit="frame")
    deforming = deforming_parts(avatar)
    transforms, offsets, largest = [], [], 0.0
    with torch.no_grad():
        avatar.prepare_sequence(bones, frame_ids=frame_ids, fps=clock_fps)
        if deforming:
            gaussians = avatar.gaussians
            grid = avatar.field.grid_weights()
            rest_means = gaussians.means.detach().contiguous()
            rest_weights = avatar.field.weights(rest_means, grid)
            vertices = torch.as_tensor(np.asarray(mesh.vertices), dtype=torch.float32, device=device)
            neighbour_index, neighbour_weight = _density_neighbours(avatar, vertices)
        for t in frames:
            pose = torch.as_tensor(bones[t], dtype=torch.float32, device=device)
            inputs = {name: torch.as_tensor(values[t], device=device) for name, values in part_inputs.items()}
            if not deforming:
                transforms.append(avatar.pose_bones(pose, inputs=inputs).cpu())
                continue
            posed = avatar.pose(pose, frame_index=t, grid=grid, inputs=inputs)
            frame_transforms = posed["bone_transforms"]
            skinned, _ = ops.lbs(rest_means, rest_weights, frame_transforms.contiguous())
            residual = posed["means"] - skinned  # [N,3] world [m]
            world = (neighbour_weight[:, :, None] * residual[neighbour_index]).sum(1)  # [V,3]
            largest = max(largest, float(world.norm(dim=-1).max()))
            offset = (_blended_inverse(mesh, frame_transforms) @ world.double()[:, :, None])[:, :, 0]
            transforms.append(frame_transforms.cpu())
            offsets.append(offset.float().cpu())
    joint_transforms = torch.stack(transforms).numpy().astype(np.float32)
    if joint_transforms.shape[1] != joint_count:
        raise ValueError(f"the avatar poses {joint_transforms.shape[1]} joints but the mesh's rig has {joint_count}")
    vertex_offsets = None
    if offsets and largest >= OFFSET_TOLERANCE:
        vertex_offsets = torch.stack(offsets).numpy().astype(np.float32)
    return MeshAnimation(joint_transforms=joint_transforms, frame_ids=frame_ids, fps=fps,
                         vertex_offsets=vertex_offsets)
