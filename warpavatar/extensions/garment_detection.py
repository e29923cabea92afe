"""Template-free detection of loose garments among an avatar's Gaussians, and of where each hangs from the body.

Why skinning weights say where cloth is. Linear blend skinning moves a point with the blend of its bones. A
point of the body proper (skin, tight clothing, a robot's rigid shell) moves with *one chain* of the skeleton:
its weights may blend a bone with its parent or child (a joint bends the skin around it), but a rigid patch of
a body never moves half with the left leg and half with the right one. Cloth that hangs *between* limbs is the
exception: a skirt's panel between the legs is pushed by both, so a fit of the skinning field gives it weights
split between chains that are not ancestors of each other (left and right thigh, an arm and the torso's other
side). That split is what the field does to explain loose cloth with skinning, the residual the issue asks for,
read off the field itself (a per-frame free-displacement stage would measure the same thing at the cost of a
stage of its own).

The rule, each threshold a geometric statement rather than a tuned number:

1. ``split`` of a Gaussian: for every pair of *unrelated* joints among its heaviest ones (neither is the
   other's ancestor), the product of their weights times how far apart the two would carry it, averaged over
   the training motion (:func:`split_motion`). The smooth fall-off of a field at a body's joints stays inside
   one chain and scores 0; weights that leak onto a neighbouring chain that moves with it (fingers side by
   side) score little because the chains hardly move apart; cloth blended half and half between the legs of
   someone walking scores a quarter of the legs' separation. Seeds: ``split >= threshold`` times the body's longest side (default 1 %: 1.7 cm on a
   1.7 m person, a sliding no point of a rigid surface does).
   The score is averaged over each point's k-NN neighbourhood first: a fitted field blends cloth patch by
   patch, with Gaussians in between that one limb explains, and a garment is a region, not scattered points.
2. Growth (hysteresis): neighbours on the k-NN graph of the canonical Gaussians whose split is at least a
   quarter of the threshold join the seeds' region (a garment's split fades towards its sides, where one leg
   dominates, but does not drop to zero while it still hangs between the limbs).
3. Connected components of that region on the k-NN graph (edges no longer than ``link`` times the median
   distance to the k-th neighbour, the surface's sampling scale: a garment is one connected surface) are kept when they hold at least
   ``min_fraction`` of all Gaussians: a crotch or an armpit, where a body's surface meets two limbs, is a
   small patch; a garment covers a sizeable part of the body.
4. Attachment: the lowest common ancestor of the two heaviest mutually unrelated joints of the component (a
   skirt split between the thighs hangs from their common ancestor, the hips); a user may name the joint.
5. Cloth hangs: a garment is held at its attachment and falls from it under gravity, so at least
   ``hang_fraction`` (half) of its Gaussians lie below that joint along the skeleton's up axis in the canonical
   pose (a skirt below the hips, the tails of a coat below the waist). A blend between chains *above* their
   common ancestor is not cloth that hangs from it: it is two body parts that pass near each other in the
   training motion (a forearm brushing the head), which the field has not separated yet.

Robots, animals and tightly dressed people should get weights inside one chain everywhere except at small
patches, so that no component passes step 3 and the fit runs exactly as without the garment extension. Known
weakness: a field that has not separated neighbouring chains yet (fingers side by side, arms against the head
in short CPU fits of the robot) scores like cloth; hence ``--garment`` is off by default for now.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from warpavatar import ops

__all__ = ["GarmentRegion", "related_joints", "split_weight", "split_motion", "lowest_common_ancestor", "detect_garments",
           "connected_components"]


@dataclass
class GarmentRegion:
    """One detected garment.

    Attributes:
        gaussian_ids: int64 ``[G]`` ascending ids of its Gaussians.
        joint: the joint it hangs from (index into the skeleton).
        split_joints: the two mutually unrelated joints its weights split between (or ``(joint, joint)``).
    """

    gaussian_ids: torch.Tensor
    joint: int
    split_joints: tuple[int, int]


def _ancestors(parents) -> list[list[int]]:
    parents = [int(p) for p in parents]
    chains = []
    for joint in range(len(parents)):
        chain, current = [], joint
        while current >= 0 and current not in chain:
            chain.append(current)
            current = parents[current]
        chains.append(chain)  # the joint, its parent, ..., its root
    return chains


def related_joints(parents) -> torch.Tensor:
    """bool ``[J, J]``: ``related[a, b]`` when ``a`` is ``b``, an ancestor or a descendant of ``b``."""
    chains = _ancestors(parents)
    count = len(chains)
    related = torch.zeros(count, count, dtype=torch.bool)
    for joint, chain in enumerate(chains):
        related[joint, chain] = True
        related[chain, joint] = True
    return related


def lowest_common_ancestor(parents, first: int, second: int) -> int:
    """The deepest joint that is ``first`` or an ancestor of it and ``second`` or an ancestor of it (-1: none)."""
    chains = _ancestors(parents)
    other = set(chains[second])
    return next((joint for joint in chains[first] if joint in other), -1)


def split_weight(weights: torch.Tensor, related: torch.Tensor) -> torch.Tensor:
    """Weight each point gives to joints unrelated to its dominant joint: ``weights [N, J]`` -> ``[N]``."""
    dominant = weights.argmax(dim=1)
    return (weights * (~related.to(weights.device)[dominant]).to(weights.dtype)).sum(dim=1)


def split_motion(means: torch.Tensor, weights: torch.Tensor, related: torch.Tensor, bone_transforms: torch.Tensor,
                 *, top: int = 4, chunk: int = 8192) -> torch.Tensor:
    """How far apart the unrelated chains a point's weights blend carry it, averaged over a motion:
    ``mean_t sum_{j < k unrelated} w_j w_k |(T_j(t) - T_k(t)) x|`` over its ``top`` heaviest joints.

    A point skinned to one chain (with any blend along it) scores 0; one blended half and half between two
    legs scores a quarter of how far apart the legs would carry it.

    Args:
        means: canonical points [world units], ``[N, 3]``.
        weights: skinning weights ``[N, J]``.
        related: :func:`related_joints` ``[J, J]``.
        bone_transforms: the motion, rest-to-posed ``[T, J, 4, 4]``.
        top: the heaviest joints of each point that are compared.

    Returns:
        ``[N]`` [world units].
    """
    top = min(top, weights.shape[1])
    heaviest, joints = weights.float().topk(top, dim=1)  # [N,K]
    pair_first, pair_second = torch.triu_indices(top, top, offset=1, device=means.device)
    related = related.to(means.device)
    homogeneous = torch.cat([means.float(), torch.ones_like(means[:, :1]).float()], dim=1)
    total = torch.zeros(means.shape[0], device=means.device)
    for transforms in bone_transforms.float().to(means.device):
        affine = transforms[:, :3, :]  # [J,3,4]
        for first in range(0, means.shape[0], chunk):
            rows = slice(first, first + chunk)
            a, b = joints[rows][:, pair_first], joints[rows][:, pair_second]  # [n,P]
            weight = heaviest[rows][:, pair_first] * heaviest[rows][:, pair_second] * (~related[a, b]).float()
            apart = torch.einsum("npab,nb->npa", affine[a] - affine[b], homogeneous[rows]).norm(dim=2)
            total[rows] += (weight * apart).sum(dim=1)
    return total / max(1, bone_transforms.shape[0])


def connected_components(selected: torch.Tensor, neighbours: torch.Tensor) -> torch.Tensor:
    """Component label of every selected point (-1 elsewhere) over symmetric k-NN links, by label propagation.

    Args:
        selected: bool ``[N]``.
        neighbours: int ``[N, k]`` neighbour ids, -1 padded (links between two selected points count both ways).

    Returns:
        int64 ``[N]``: the smallest point id of each point's component, -1 for points not selected.
    """
    count = selected.shape[0]
    ids = torch.arange(count, device=selected.device)
    rows = ids[:, None].expand_as(neighbours).reshape(-1)
    columns = neighbours.reshape(-1).long()
    keep = columns >= 0
    rows, columns = rows[keep], columns[keep]
    keep = selected[rows] & selected[columns]
    first = torch.cat([rows[keep], columns[keep]])
    second = torch.cat([columns[keep], rows[keep]])
    big = torch.iinfo(torch.int64).max
    label = torch.where(selected, ids, torch.full_like(ids, big))
    while True:
        update = label.clone().scatter_reduce_(0, first, label[second], reduce="amin")
        # pointer jumping: a label is a point of the same component, whose own label is at least as small
        update = torch.where(selected, update[torch.where(selected, update, ids)], update)
        if torch.equal(update, label):
            break
        label = update
    return torch.where(selected, label, torch.full_like(label, -1))


@torch.no_grad()
def detect_garments(
    means: torch.Tensor,
    weights: torch.Tensor,
    parents,
    bone_transforms: torch.Tensor,
    *,
    threshold: float = 0.005,
    min_fraction: float = 0.03,
    neighbours: int = 8,
    link: float = 2.0,
    heads: torch.Tensor | None = None,
    up: torch.Tensor | None = None,
    hang_fraction: float = 0.5,
) -> list[GarmentRegion]:
    """Find the garments among canonical Gaussians from their skinning weights (see the module docstring).

    Args:
        means: canonical centres [world units], float ``[N, 3]``.
        weights: skinning weights per skeleton joint, float ``[N, J]`` (rows summing to about 1).
        parents: parent of each joint ``[J]`` (-1: a root).
        bone_transforms: the training motion ``[T, J, 4, 4]``.
        threshold: :func:`split_motion` of a seed, as a fraction of the canonical points' longest side.
        min_fraction: smallest garment as a fraction of all Gaussians, ``(0, 1)``.
        neighbours: k of the k-NN graph the components are found on.
        link: longest link of that graph, in median distances to the k-th neighbour.
        heads: canonical joint positions ``[J, 3]`` [world units] and ``up``: the skeleton's up axis ``[3]``; with
            both, a region counts only when at least ``hang_fraction`` of its Gaussians lie below its attachment
            joint (rule 5 of the module docstring).
        hang_fraction: see ``heads``, ``[0, 1]``.

    Returns:
        The garments, largest first (empty when there is none).
    """
    if not 0.0 < threshold < 1.0 or not 0.0 < min_fraction < 1.0:
        raise ValueError(f"threshold and min_fraction must be in (0, 1), got {threshold} and {min_fraction}")
    if not 0.0 <= hang_fraction <= 1.0:
        raise ValueError(f"hang_fraction must be in [0, 1], got {hang_fraction}")
    count = means.shape[0]
    if count < 2:
        return []
    related = related_joints(parents)
    extent = float((means.max(0).values - means.min(0).values).max())
    split = split_motion(means, weights.float(), related, bone_transforms) / max(extent, 1e-12)
    index, distance = ops.knn_graph(means.detach().float().contiguous(), min(neighbours, count - 1))
    valid = index >= 0
    # the sampling scale of the surface: the median distance to the k-th neighbour (the nearest one is no
    # scale: density control leaves clones almost on top of each other)
    last = distance[:, -1][valid[:, -1]]
    spacing = last.median() if last.numel() else torch.tensor(0.0)
    index = torch.where(valid & (distance <= link * spacing), index, -1)
    # a garment is a surface region, not scattered points: score each point by the mean over itself and its
    # linked neighbours (a fitted field blends cloth patch by patch, with single Gaussians in between that
    # one leg explains)
    linked = index >= 0
    gathered = torch.where(linked, split[index.clamp_min(0)], torch.zeros_like(distance))
    split = (split + gathered.sum(dim=1)) / (1.0 + linked.sum(dim=1))
    region = split >= threshold
    weak = split >= 0.25 * threshold
    while True:  # grow the seeds through neighbours that are split at least weakly
        reached = region.clone()
        reached[index[region].reshape(-1)[index[region].reshape(-1) >= 0]] = True
        grown = region | (reached & weak)
        if torch.equal(grown, region):
            break
        region = grown
    labels = connected_components(region, index)
    found = []
    unique, sizes = torch.unique(labels[labels >= 0], return_counts=True)
    for label, size in zip(unique.tolist(), sizes.tolist()):
        if size < min_fraction * count:
            continue
        ids = torch.nonzero(labels == label).reshape(-1)
        mass = weights[ids].float().sum(dim=0)
        first = int(mass.argmax())
        unrelated = torch.where(related[first].to(mass.device), torch.full_like(mass, -1.0), mass)
        second = int(unrelated.argmax()) if bool((unrelated > 0).any()) else first
        joint = lowest_common_ancestor(parents, first, second)
        joint = joint if joint >= 0 else first
        if heads is not None and up is not None:
            axis = torch.as_tensor(up, dtype=torch.float32, device=means.device)
            axis = axis / axis.norm().clamp_min(1e-12)
            joint_height = torch.as_tensor(heads, dtype=torch.float32, device=means.device)[joint] @ axis
            below = (means[ids].float() @ axis <= joint_height).float().mean()
            if float(below) < hang_fraction:
                continue  # not hanging from its attachment (rule 5)
        found.append(GarmentRegion(ids, joint, (first, second)))
    found.sort(key=lambda region: -region.gaussian_ids.numel())
    return found
