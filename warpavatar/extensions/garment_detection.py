"""Template-free detection of loose garments among an avatar's Gaussians, and of where each hangs from the body.

Why skinning weights say where cloth is. Linear blend skinning moves a point with the blend of its bones. A
point of the body proper (skin, tight clothing, a robot's rigid shell) moves with *one chain* of the skeleton:
its weights may blend a bone with its parent or child (a joint bends the skin around it), but a rigid patch of
a body never moves half with the left leg and half with the right one. Cloth that hangs *between* limbs is the
exception: a skirt's panel between the legs is pushed by both, so a fit of the skinning field gives it weights
split between chains that are not ancestors of each other (left and right thigh, the two arms under a poncho, a
leg and the spine under a dress). That split is what the field does to explain loose cloth with skinning, the
residual the issue asks for, read off the field itself. Where the fit also learns free per-frame offsets of the
Gaussians (``offsets``: motion skinning left unexplained), they are a second, direct reading of the same residual.

The rule, each threshold a geometric statement rather than a tuned number (``H``: the body's height along the
up axis):

1. ``split`` of a Gaussian: for every pair of *unrelated* joints among its heaviest ones (neither is the
   other's ancestor), the product of their weights times how far apart the two would carry it, averaged over
   the training motion (:func:`split_motion`). The smooth fall-off of a field at a body's joints stays inside
   one chain and scores 0; weights that leak onto a neighbouring chain that moves with it (fingers side by
   side) score little because the chains hardly move apart; cloth blended half and half between the legs of
   someone walking scores a quarter of the legs' separation. A pair counts only when it can be cloth pushed by
   both limbs:

   - each joint has at least ``min_weight`` (10 %) of the weight: a trace of a far joint's weight is noise of
     the field, not a second limb pushing;
   - the point lies near both chains (within ``near``, a fifth of ``H``, of a bone segment of each joint's chain
     from the joint up to the two joints' lowest common ancestor): cloth between two limbs touches both, or
     the body where they meet (a poncho's front hangs from the chest between the arms), while a lower leg
     carrying a trace of the head's weight lies half a body away from the head, the neck, the chest, the spine
     and the hips (on the H100 such blends passed the product alone: weight x weight x distance is large for
     far-apart joints even when the weight is tiny);
   - the two bones lie farther apart than one voxel of the skinning field (``resolution``): closer bones (the
     fingers of a hand) share voxels, and their blend is the field's interpolation, whatever the images say.

   With ``offsets``, a Gaussian's score is the larger of its split and the mean length of its offset over the
   frames (how far skinning alone misplaces it). Seeds: a score of at least ``threshold`` times the body's
   longest side (default 0.5 %: 8 mm on a 1.7 m person, a sliding no point of a rigid surface does). The score
   is averaged over each point's k-NN neighbourhood first: a fitted field blends cloth patch by patch, with
   Gaussians in between that one limb explains, and a garment is a region, not scattered points.
2. Hysteresis: neighbours on the k-NN graph of the canonical Gaussians whose score is at least a quarter of
   the threshold join the seeds' region (a garment's split fades towards its sides, where one limb dominates).
3. Connected components of that region on the k-NN graph (edges no longer than ``link`` times the median
   distance to the k-th neighbour, the surface's sampling scale: a garment is one connected surface) are seed
   regions when they hold at least ``seed_fraction`` (0.5 %) of all Gaussians, and a garment, once grown (rule
   6), when it holds at least ``min_fraction`` (3 %): a crotch or an armpit, where a body's surface meets two
   limbs, is a small patch; a garment covers a sizeable part of the body.
4. The anchor: where the two chains that push the cloth meet. The pair of mutually unrelated joints holding the
   most blended weight over the seed region (the sum of their weights' product) splits it; their lowest common
   ancestor is the anchor: the hips for a blend of the two legs (a skirt, a dress's skirt, a coat's tails) or of
   a leg and the spine (a dress that flares from above the hips), the chest for a blend of the two arms (a
   poncho, a cape). A region with no unrelated blend (one found by its offsets alone) is anchored at its
   heaviest joint.
5. Cloth hangs: gravity pulls it down from where it is held. Its hem (the seeds' lowest point, but for the
   lowest 2 %, stray points) lies at least ``min_length`` (15 %) of ``H`` below where the pushing limbs leave
   the body (the highest of the anchor's head and the heads of the anchor's two children towards the split
   joints: the hips for the legs, the shoulders for the arms), as the shortest skirt does; and at least
   ``hang_fraction`` (half) of its seeds lie below the top of the bone of the joint it hangs from (rule 7; the
   higher of the bone's two ends along the up axis, its head without ``tails``) in the canonical pose. A blend
   between chains *above* their common ancestor is not cloth that hangs from it: it is two body parts that pass
   near each other in the training motion (a forearm brushing the head), which the field has not separated
   yet; a blended patch that hangs only a hand's length (the fingers below a wrist, a crotch below the hips)
   is too short to swing as cloth.
6. The whole garment: the seeds are where the cloth lies *between* the limbs; the panels in front of and
   behind them move with one limb each (or with the torso), so their weights are that limb's and they score
   nothing. The seed region grows through its neighbours on the k-NN graph that are skinned mostly to

   - the anchor, or a joint of the branches below it that hold the two split joints (a skirt's panels over
     each leg, a poncho's over each arm), no farther along that branch's bones than the seeds reach along them
     or than the branch's bones take to come down to the hem, whichever is farther (the height bound below
     then cuts what hangs lower: a leg below a skirt's hem, a forearm below a poncho's; an arm held out level
     is cloth no farther out than the seeds), or
   - a joint the cloth may hang from above the anchor (its ancestors, and its descendants off the split
     branches whose head lies above its own: the spine and chest above the hips) whose head lies below the top
     of the growth,

   and that lie between the hem and the top of the growth: the top of the anchor's bone or the seeds' top (but
   for the highest 2 %), whichever is higher (a skirt hangs from the waist; the torso above it stays body).
   Above that top the garment continues only through neighbours that the field still shows pushed by two
   unrelated chains (two of them with at least ``min_weight`` each, near their bones or not): the upper part
   of a dress that hangs from the chest, whose leg weights fade towards its top. Two seed regions that grow
   into each other (a skirt's front and back) are one garment.
7. Attachment: a garment is held where it moves with one joint, at its top ring (its Gaussians within the
   highest tenth of its height). Among the anchor and the joints it may hang from above it (rule 6) whose head
   lies at or below the ring's bottom (the ring lies on their bone), the attachment is the one that holds the
   most of the ring's weight: the hips for a skirt, the chest for a dress or tunic whose top ring is at the
   chest, the chest (the shoulders' joint) for a poncho. A user may name the joint instead. Cloth hangs *from*
   its attachment: the garment's top (but for the highest 2 %) lies within ``reach`` (10 %) of ``H`` below the
   attachment's head, as a skirt's waistband is at the hips. A blend of the two shins that nothing joins to the
   hips (a fitted robot's legs, seen on the H100) is two limbs the field has not separated yet, however far
   below the hips it hangs.

8. Skinning does not explain cloth (checked by the garment extension, which holds the images): the avatar
   draws a garment worse than the rest of itself. Over the training frames, the mean absolute image error of
   the region's pixels (each weighted by the region's share of its opacity) exceeds the rest's by at least
   ``--garment-residual`` (0.02 of the intensity range). On the H100, default preset, steps 3000-5000: the
   cesium skirt's regions exceed the rest by 0.034-0.053; a blend of a fitted robot's hips and thigh that
   passed rules 1-7 (a field not yet settled) by 0.007.

Which garments are found, and where they hang. ``tests/test_garment_detection.py`` dresses a skinned, walking
figure: a skirt (split between the legs: anchored and hung at the hips), a tunic hung from the chest down to the
knees (split between the legs, anchored at the hips; the leg weights fade up to its top ring, which moves with
the chest: hung from the chest), a poncho from the shoulders (split between the arms: anchored and hung at the
chest, the arms' parent), and finds none on the bare figure (its crotch scores little and hangs too short; its
armpits blend an arm with its own parent, one chain) or on fingers side by side that curl against each other
(too short). A cape (the arms above, the legs below) and a coat's tails (the legs, hung from the hips or the
spine, whichever their top ring moves with) follow the same rules but are not built there. A garment must hang
15 % of ``H`` below the hips (rule 5: a hem at about 30 % of the height, just above the knees, or lower); a mini
skirt is not found. Rules 5-7 need the bones
(``heads``, ``tails`` and ``up``); without them the seeds are grown by score and size only, and hang from their
anchor.

Robots, animals and tightly dressed people should get weights inside one chain everywhere except at small
patches, so that no region passes rules 3 and 5 and the fit runs exactly as without the garment extension.
On the H100 a field still settling does blend a robot's legs now and then (two robot fits of this kind: at
step 3000 of one, at step 5000 of another), so rule 8 is the last word. ``research/garment_report.py`` runs
rules 1-7 on a saved avatar.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from warpavatar import ops

__all__ = ["GarmentRegion", "related_joints", "split_weight", "split_motion", "lowest_common_ancestor", "detect_garments",
           "connected_components", "bone_gaps"]


@dataclass
class GarmentRegion:
    """One detected garment.

    Attributes:
        gaussian_ids: int64 ``[G]`` ascending ids of its Gaussians.
        joint: the joint it hangs from (index into the skeleton).
        split_joints: the two mutually unrelated joints its weights split between (or ``(joint, joint)``).
        anchor: where those two chains meet, their lowest common ancestor (rule 4; -1: not recorded); ``joint``
            is the anchor or a joint above it that the garment's top ring moves with (rule 7).
    """

    gaussian_ids: torch.Tensor
    joint: int
    split_joints: tuple[int, int]
    anchor: int = -1


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


def _segment_distance(points: torch.Tensor, heads: torch.Tensor, tails: torch.Tensor, joints: torch.Tensor
                      ) -> torch.Tensor:
    """Distance of each point to the bone segments of the given joints [world units]: ``points [N,3]`` and
    ``joints [N,P]`` -> ``[N,P]``."""
    start, end = heads[joints], tails[joints]  # [N,P,3]
    along = end - start
    t = (((points[:, None] - start) * along).sum(-1) / (along * along).sum(-1).clamp_min(1e-12)).clamp(0.0, 1.0)
    return (points[:, None] - (start + t[..., None] * along)).norm(dim=-1)


def _paths_to_common_ancestor(parents) -> torch.Tensor:
    """bool ``[J, J, J]``: ``paths[a, b, k]`` when joint ``k`` lies on the chain from ``a`` up to the lowest common
    ancestor of ``a`` and ``b`` (both included; ``a``'s whole chain when they share no root)."""
    chains = _ancestors(parents)
    count = len(chains)
    paths = torch.zeros(count, count, count, dtype=torch.bool)
    for a in range(count):
        for b in range(count):
            common = set(chains[b])
            chain = chains[a]
            end = next((i for i, joint in enumerate(chain) if joint in common), len(chain) - 1)
            paths[a, b, chain[:end + 1]] = True
    return paths


def split_motion(means: torch.Tensor, weights: torch.Tensor, related: torch.Tensor, bone_transforms: torch.Tensor,
                 *, top: int = 4, chunk: int = 8192, min_weight: float = 0.0, heads: torch.Tensor | None = None,
                 tails: torch.Tensor | None = None, near: float = float("inf"), parents=None) -> torch.Tensor:
    """How far apart the unrelated chains a point's weights blend carry it, averaged over a motion:
    ``mean_t sum_{j < k unrelated} w_j w_k |(T_j(t) - T_k(t)) x|`` over its ``top`` heaviest joints.

    A point skinned to one chain (with any blend along it) scores 0; one blended half and half between two
    legs scores a quarter of how far apart the legs would carry it. A pair counts only when both of its weights
    are at least ``min_weight`` and, with ``heads`` and ``tails``, when the point lies within ``near`` of both
    joints' bone segments, or with ``parents`` of each joint's chain up to the pair's lowest common ancestor
    (rule 1 of the module docstring).

    Args:
        means: canonical points [world units], ``[N, 3]``.
        weights: skinning weights ``[N, J]``.
        related: :func:`related_joints` ``[J, J]``.
        bone_transforms: the motion, rest-to-posed ``[T, J, 4, 4]``.
        top: the heaviest joints of each point that are compared.
        min_weight: smallest weight of either joint of a pair that counts, ``[0, 1)``.
        heads: canonical bone starts ``[J, 3]`` and ``tails`` their ends [world units], for ``near``.
        near: farthest a point may lie from either bone of a pair that counts [world units].
        parents: parent of each joint ``[J]``: with it, ``near`` is measured to the nearest bone of each joint's
            chain from the joint up to the pair's lowest common ancestor (both included).

    Returns:
        ``[N]`` [world units].
    """
    top = min(top, weights.shape[1])
    heaviest, joints = weights.float().topk(top, dim=1)  # [N,K]
    pair_first, pair_second = torch.triu_indices(top, top, offset=1, device=means.device)
    related = related.to(means.device)
    homogeneous = torch.cat([means.float(), torch.ones_like(means[:, :1]).float()], dim=1)
    total = torch.zeros(means.shape[0], device=means.device)
    pair_weights = []
    paths = None
    for first in range(0, means.shape[0], chunk):
        rows = slice(first, first + chunk)
        a, b = joints[rows][:, pair_first], joints[rows][:, pair_second]  # [n,P]
        wa, wb = heaviest[rows][:, pair_first], heaviest[rows][:, pair_second]
        counts = ~related[a, b] & (torch.minimum(wa, wb) >= min_weight)
        if heads is not None and tails is not None:
            points = means[rows].float()
            heads_, tails_ = heads.float().to(means.device), tails.float().to(means.device)
            if parents is None:
                counts &= (_segment_distance(points, heads_, tails_, a) <= near)
                counts &= (_segment_distance(points, heads_, tails_, b) <= near)
            else:
                if paths is None:
                    paths = _paths_to_common_ancestor(parents).to(means.device)
                every = torch.arange(heads_.shape[0], device=means.device).expand(points.shape[0], -1)
                distance = _segment_distance(points, heads_, tails_, every)[:, None, :]  # [n,1,J]
                far = torch.tensor(float("inf"), device=means.device)
                counts &= torch.where(paths[a, b], distance, far).amin(dim=2) <= near
                counts &= torch.where(paths[b, a], distance, far).amin(dim=2) <= near
        pair_weights.append(wa * wb * counts.float())
    pair_weight = torch.cat(pair_weights)
    for transforms in bone_transforms.float().to(means.device):
        affine = transforms[:, :3, :]  # [J,3,4]
        for first in range(0, means.shape[0], chunk):
            rows = slice(first, first + chunk)
            a, b = joints[rows][:, pair_first], joints[rows][:, pair_second]  # [n,P]
            apart = torch.einsum("npab,nb->npa", affine[a] - affine[b], homogeneous[rows]).norm(dim=2)
            total[rows] += (pair_weight[rows] * apart).sum(dim=1)
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


def bone_gaps(heads: torch.Tensor, tails: torch.Tensor, *, samples: int = 17) -> torch.Tensor:
    """Shortest distance between every two bone segments [world units], ``[J, J]`` (each segment sampled at
    ``samples`` evenly spaced points, so within ``1 / (samples - 1)`` of a bone's length of the exact value)."""
    t = torch.linspace(0.0, 1.0, samples, device=heads.device)
    points = heads[:, None] + t[None, :, None] * (tails - heads)[:, None]  # [J,S,3]
    flat = points.reshape(-1, 3)
    distances = torch.cdist(flat, flat).reshape(heads.shape[0], samples, heads.shape[0], samples)
    return distances.amin(dim=(1, 3))


def _subtree(parents, root: int) -> list[int]:
    """``root`` and every joint below it."""
    return [joint for joint, chain in enumerate(_ancestors(parents)) if root in chain]


def _child_towards(parents, joint: int, descendant: int) -> int:
    """The child of ``joint`` on the way to ``descendant`` (``descendant`` itself when it is ``joint``)."""
    chain = _ancestors(parents)[descendant]
    return chain[chain.index(joint) - 1] if joint in chain and descendant != joint else descendant


def _flood(region: torch.Tensor, allowed: torch.Tensor, neighbours: torch.Tensor) -> torch.Tensor:
    """``region`` grown through the ``allowed`` points it reaches on the k-NN graph (bool ``[N]``)."""
    while True:
        links = neighbours[region].reshape(-1)
        reached = torch.zeros_like(region)
        reached[links[links >= 0]] = True
        grown = region | (reached & allowed)
        if torch.equal(grown, region):
            return region
        region = grown


def _unrelated_pair(weights: torch.Tensor, ignored: torch.Tensor) -> tuple[int, int]:
    """The two joints, not ``ignored`` as a pair, that hold the most blended weight over ``weights [G, J]`` (the
    sum over the points of their weights' product), heavier first; ``(heaviest, heaviest)`` when no such two
    share a point (rule 4)."""
    weights = weights.float()
    mass = weights.sum(dim=0)
    product = weights.T @ weights  # [J,J]
    product = torch.where(ignored.to(product.device), torch.zeros_like(product), product)
    if not bool((product > 0).any()):
        heaviest = int(mass.argmax())
        return heaviest, heaviest
    first, second = divmod(int(product.argmax()), product.shape[1])
    return (first, second) if float(mass[first]) >= float(mass[second]) else (second, first)


def _two_chains(weights: torch.Tensor, ignored: torch.Tensor, min_weight: float, *, top: int = 4) -> torch.Tensor:
    """bool ``[N]``: points whose weights ``[N, J]`` hold two joints, not ``ignored`` as a pair, with at least
    ``min_weight`` (and more than 0) each: moved by two unrelated chains (rule 6)."""
    top = min(top, weights.shape[1])
    heaviest, joints = weights.float().topk(top, dim=1)
    first, second = torch.triu_indices(top, top, offset=1, device=weights.device)
    lighter = torch.minimum(heaviest[:, first], heaviest[:, second])
    pairs = ~ignored.to(weights.device)[joints[:, first], joints[:, second]] & (lighter >= min_weight) & (lighter > 0)
    return pairs.any(dim=1)


def _hang_candidates(parents, anchor: int, branches: set[int], head_heights: torch.Tensor) -> list[int]:
    """The joints a garment anchored at ``anchor`` may hang from above it: its ancestors, and its descendants off
    the split ``branches`` whose head lies higher than its own (rule 6)."""
    chains = _ancestors(parents)
    above = list(chains[anchor][1:])
    for joint, chain in enumerate(chains):
        if (joint != anchor and anchor in chain and joint not in branches
                and float(head_heights[joint]) > float(head_heights[anchor])):
            above.append(joint)
    return above


def _branch_starts(heads: torch.Tensor, parents, root: int) -> tuple[list[int], list[float]]:
    """The joints of the branch below ``root`` (``root`` and its descendants) and how far along the chain of heads
    each one's head lies from ``root``'s [world units]."""
    chains = _ancestors(parents)
    joints = _subtree(parents, root)
    starts = []
    for joint in joints:
        path = chains[joint][:chains[joint].index(root) + 1]  # joint, its parent, ..., root
        starts.append(sum(float((heads[path[i]] - heads[path[i + 1]]).norm()) for i in range(len(path) - 1)))
    return joints, starts


def _branch_arclength(points: torch.Tensor, heads: torch.Tensor, tails: torch.Tensor, parents, root: int
                      ) -> torch.Tensor:
    """How far along the bones of the branch below ``root`` each point lies [world units], ``points [N,3]`` ->
    ``[N]``: the distance along the branch from ``root``'s head to the nearest point of its nearest bone segment."""
    if points.shape[0] == 0:
        return torch.zeros(0, device=points.device)
    joints, starts = _branch_starts(heads, parents, root)
    ids = torch.tensor(joints, dtype=torch.long, device=points.device)
    start = torch.tensor(starts, dtype=torch.float32, device=points.device)
    nearest = _segment_distance(points, heads, tails, ids.expand(points.shape[0], -1)).argmin(dim=1)
    bone_start, bone_end = heads[ids[nearest]], tails[ids[nearest]]
    along = bone_end - bone_start
    length = along.norm(dim=1)
    t = (((points - bone_start) * along).sum(dim=1) / (length * length).clamp_min(1e-12)).clamp(0.0, 1.0)
    return start[nearest] + t * length


def _descent(heads: torch.Tensor, tails: torch.Tensor, parents, root: int, axis: torch.Tensor, level: float
             ) -> float:
    """How far along the branch below ``root`` its bones first come down to the height ``level`` along ``axis``
    [world units] (0 when they never do)."""
    joints, starts = _branch_starts(heads, parents, root)
    crossings = []
    for joint, start in zip(joints, starts):
        high, low = float(heads[joint] @ axis), float(tails[joint] @ axis)
        length = float((tails[joint] - heads[joint]).norm())
        if high <= level:
            crossings.append(start)
        elif low <= level:
            crossings.append(start + length * (high - level) / (high - low))
    return min(crossings, default=0.0)


def _branch_roots(parents, anchor: int, first: int, second: int) -> list[int]:
    """The children of ``anchor`` that lead to the split joints ``first`` and ``second`` (none when they are one
    joint: a region found by its offsets alone)."""
    if first == second:
        return []
    chains = _ancestors(parents)
    return sorted({_child_towards(parents, anchor, split) for split in (first, second)
                   if split != anchor and anchor in chains[split]})


def _quantile(values: torch.Tensor, fraction: float) -> float:
    """The ``fraction`` quantile of ``values`` (a sample of it: the k-th smallest), as the rules' 2 % trims."""
    return float(values.kthvalue(1 + int(fraction * (values.numel() - 1))).values)


@torch.no_grad()
def _merge_overlapping(grown: list[tuple], region: tuple) -> list[tuple]:
    """Add a grown region ``(mask [N] bool, joint, first, second, anchor)`` to ``grown``, merged with every
    region there that it overlaps (two seed regions of one garment, its front and back, grew into each other); a
    merged region keeps the joints of its largest part."""
    garment, *joints = region
    overlapping = [bool((other[0] & garment).any()) for other in grown]
    largest = int(garment.sum())
    for other, overlaps in zip(grown, overlapping):
        if overlaps:
            if int(other[0].sum()) > largest:
                largest, joints = int(other[0].sum()), list(other[1:])
            garment = garment | other[0]
    return [other for other, overlaps in zip(grown, overlapping) if not overlaps] + [(garment, *joints)]


def detect_garments(
    means: torch.Tensor,
    weights: torch.Tensor,
    parents,
    bone_transforms: torch.Tensor,
    *,
    threshold: float = 0.005,
    min_fraction: float = 0.03,
    seed_fraction: float = 0.005,
    min_weight: float = 0.1,
    near: float = 0.2,
    resolution: float = 0.0,
    neighbours: int = 32,
    smoothing: int = 8,
    link: float = 1.0,
    heads: torch.Tensor | None = None,
    tails: torch.Tensor | None = None,
    up: torch.Tensor | None = None,
    hang_fraction: float = 0.5,
    min_length: float = 0.15,
    reach: float = 0.1,
    offsets: torch.Tensor | None = None,
) -> list[GarmentRegion]:
    """Find the garments among canonical Gaussians from their skinning weights (see the module docstring).

    Args:
        means: canonical centres [world units], float ``[N, 3]``.
        weights: skinning weights per skeleton joint, float ``[N, J]`` (rows summing to about 1).
        parents: parent of each joint ``[J]`` (-1: a root).
        bone_transforms: the training motion ``[T, J, 4, 4]``.
        threshold: a seed's score (:func:`split_motion`, or its offsets), as a fraction of the canonical points'
            longest side.
        min_fraction: smallest garment as a fraction of all Gaussians, ``(0, 1)``.
        seed_fraction: smallest connected region of seeds a garment grows from, as a fraction of all Gaussians,
            ``(0, 1)`` (rule 3).
        min_weight: smallest weight of the lighter joint of a blend that makes a seed, ``[0, 1)`` (rule 1), or
            that carries a garment above its seeds (rule 6).
        near: with ``heads`` and ``tails``, farthest a seed may lie from either bone it blends, as a fraction of
            the body's height along ``up`` (or of its longest side without ``up``), ``> 0`` (rule 1).
        resolution: with ``heads`` and ``tails``, the skinning field's voxel size [world units]: a blend of two
            bones closer together than this is the field's interpolation and makes no seed (rule 1).
        neighbours: k of the k-NN graph the components are found on: enough to reach past a Gaussian's clones
            (density control leaves several almost on top of each other; with 8, six clones of each Gaussian broke
            a fitted avatar's graph into over a thousand components and the skirt was not found).
        smoothing: how many of those neighbours (the nearest) each point's score is averaged over (rule 1).
        link: longest link of that graph, in median distances to the k-th neighbour (1: on a surface sampled
            evenly, about twice the distance to the 8th; longer links jump between body parts, as from a robot's
            arm to its legs in a fit whose field was not trained yet).
        heads: canonical joint positions (bone starts) ``[J, 3]`` [world units]; ``tails``: the bones' ends
            ``[J, 3]``; ``up``: the skeleton's up axis ``[3]``. With ``heads`` and ``tails``, blends count only
            between bones near the point (rule 1); with ``heads`` and ``up``, a region counts only when it hangs
            past its anchor (rule 5) and reaches up to its attachment (rule 7); with all three, each region is
            grown into the whole garment (rule 6) and hung from the joint its top ring moves with (rule 7).
            Without them: seeds, growth by score and size only, hung from the anchor (rule 4).
        hang_fraction: see ``heads``, ``[0, 1]``.
        min_length: with ``heads`` and ``up``, how far at least a garment's seeds reach below the top of its
            anchor's bone, as a fraction of the body's height, ``[0, 1)`` (rule 5).
        reach: with ``heads`` and ``up``, how far at most a garment's top may lie below its attachment joint, as a
            fraction of the body's height, ``[0, 1)`` (rule 7).
        offsets: optional free offsets the fit added to each Gaussian's canonical position before skinning in
            each training frame [world units], float ``[T', N, 3]`` (for instance the secondary-motion
            extension's node displacements blended to the Gaussians): the motion skinning did not explain. With
            them, a Gaussian's score is the larger of its split and its mean offset length (rule 1).

    Returns:
        The garments, largest first (empty when there is none).
    """
    for name, value in (("threshold", threshold), ("min_fraction", min_fraction), ("seed_fraction", seed_fraction)):
        if not 0.0 < value < 1.0:
            raise ValueError(f"{name} must be in (0, 1), got {value}")
    if not 0.0 <= hang_fraction <= 1.0:
        raise ValueError(f"hang_fraction must be in [0, 1], got {hang_fraction}")
    if not 0.0 <= reach < 1.0:
        raise ValueError(f"reach must be in [0, 1), got {reach}")
    if not 0.0 <= min_weight < 1.0 or not 0.0 <= min_length < 1.0 or not near > 0.0:
        raise ValueError(f"min_weight and min_length must be in [0, 1) and near > 0, got {min_weight}, {min_length} "
                         f"and {near}")
    count = means.shape[0]
    if offsets is not None and (offsets.dim() != 3 or offsets.shape[1:] != (count, 3)):
        raise ValueError(f"offsets must have shape [T, {count}, 3] (one offset per Gaussian and frame), got "
                         f"{list(offsets.shape)}")
    if count < 2:
        return []
    related = related_joints(parents)
    means = means.detach().float()
    weights = weights.detach().float()
    extent = float((means.max(0).values - means.min(0).values).max())
    axis = None if up is None else torch.as_tensor(up, dtype=torch.float32, device=means.device)
    if axis is not None:
        axis = axis / axis.norm().clamp_min(1e-12)
        height = means @ axis
        body_height = float(height.max() - height.min())
    else:
        body_height = extent
    heads = None if heads is None else torch.as_tensor(heads, dtype=torch.float32, device=means.device)
    tails = None if tails is None else torch.as_tensor(tails, dtype=torch.float32, device=means.device)
    ignored = related.clone()  # pairs of joints whose blend is no evidence of cloth
    if heads is not None and tails is not None and resolution > 0.0:
        ignored |= (bone_gaps(heads, tails) < resolution).cpu()  # interpolation of the field, not cloth (rule 1)
    score = split_motion(means, weights, ignored, bone_transforms, min_weight=min_weight, heads=heads,
                         tails=tails, near=near * body_height, parents=parents) / max(extent, 1e-12)
    if offsets is not None:  # how far skinning alone misplaces each Gaussian, averaged over the frames
        moved = torch.zeros(count, device=means.device)
        for frame in offsets.detach():
            moved += frame.float().to(means.device).norm(dim=1)
        score = torch.maximum(score, moved / max(1, offsets.shape[0]) / max(extent, 1e-12))
    index, distance = ops.knn_graph(means.contiguous(), min(neighbours, count - 1))
    valid = index >= 0
    # the sampling scale of the surface: the median distance to the k-th neighbour (the nearest one is no
    # scale: density control leaves clones almost on top of each other)
    last = distance[:, -1][valid[:, -1]]
    spacing = last.median() if last.numel() else torch.tensor(0.0)
    index = torch.where(valid & (distance <= link * spacing), index, -1)
    # a garment is a surface region, not scattered points: score each point by the mean over itself and its
    # linked neighbours (a fitted field blends cloth patch by patch, with single Gaussians in between that
    # one leg explains)
    near_index = index[:, :smoothing]  # nearest first
    linked = near_index >= 0
    gathered = torch.where(linked, score[near_index.clamp_min(0)], torch.zeros_like(score)[:, None])
    score = (score + gathered.sum(dim=1)) / (1.0 + linked.sum(dim=1))
    region = _flood(score >= threshold, score >= 0.25 * threshold, index)  # hysteresis (rule 2)
    labels = connected_components(region, index)
    dominant = weights.argmax(dim=1)
    head_heights = None if heads is None or axis is None else heads @ axis
    bone_tops = head_heights if tails is None or head_heights is None else torch.maximum(head_heights, tails @ axis)
    grown = []  # (bool [N], attachment, first, second, anchor) per garment
    unique, sizes = torch.unique(labels[labels >= 0], return_counts=True)
    for label, size in zip(unique.tolist(), sizes.tolist()):
        if size < seed_fraction * count:
            continue
        seeds = labels == label
        first, second = _unrelated_pair(weights[seeds], ignored)  # rule 4
        anchor = lowest_common_ancestor(parents, first, second)
        anchor = anchor if anchor >= 0 else first
        joint, garment = anchor, seeds
        if head_heights is not None:
            anchor_top = float(bone_tops[anchor])
            # where the cloth is held: the highest of the anchor and the two limbs' roots (the hip joints, the
            # shoulders)
            held = max(float(head_heights[limb]) for limb in [anchor] + _branch_roots(parents, anchor, first, second))
            seed_heights = height[seeds]
            hem = _quantile(seed_heights, 0.02)  # the seeds' lowest point, but for the lowest 2 % (stray points)
            if hem > held - min_length * body_height:
                continue  # too short to swing: fingers below a wrist, a crotch below the hips (rule 5)
            if tails is not None:
                garment, joint = _grow(seeds, anchor, first, second, hem, anchor_top, means, weights, dominant,
                                       height, axis, parents, heads, tails, head_heights, index, ignored,
                                       min_weight)
            if float((seed_heights <= float(bone_tops[joint])).float().mean()) < hang_fraction:
                continue  # above the joint it would hang from: not hanging from it (rule 5)
            # rule 7: cloth hangs *from* its attachment, so the garment reaches up to it (its top, but for the
            # highest 2 %, within `reach` of the body's height below the joint): a blend between the shins that
            # nothing joins to the hips is two legs the field has not separated yet
            if _quantile(height[garment], 0.98) < float(head_heights[joint]) - reach * body_height:
                continue
        grown = _merge_overlapping(grown, (garment, joint, first, second, anchor))
    found = [GarmentRegion(torch.nonzero(garment).reshape(-1), joint, (first, second), anchor)
             for garment, joint, first, second, anchor in grown
             if int(garment.sum()) >= min_fraction * count]  # a crotch or an armpit is no garment (rule 3)
    found.sort(key=lambda region: -region.gaussian_ids.numel())
    return found


def _grow(seeds, anchor, first, second, hem, anchor_top, means, weights, dominant, height, axis, parents, heads,
          tails, head_heights, index, ignored, min_weight) -> tuple[torch.Tensor, int]:
    """Rules 6 and 7 for one seed region: the whole garment (bool ``[N]``) and the joint it hangs from."""
    device = means.device
    branches = {root: set(_subtree(parents, root)) for root in _branch_roots(parents, anchor, first, second)}
    in_branch = set().union(*branches.values()) if branches else set()
    above = _hang_candidates(parents, anchor, in_branch, head_heights)
    top = max(anchor_top, _quantile(height[seeds], 0.98))  # the top of the growth
    holding = torch.zeros(weights.shape[1], dtype=torch.bool, device=device)  # joints the cloth may be skinned to
    holding[anchor] = True
    holding[[joint for joint in above if float(head_heights[joint]) < top]] = True
    climbing = holding.clone()  # above the top: the joints a garment that continues upwards may be skinned to
    climbing[above] = True
    along = torch.ones_like(seeds)  # no farther along a split branch than the seeds reach along it
    for root, members in branches.items():
        member = torch.zeros(weights.shape[1], dtype=torch.bool, device=device)
        member[sorted(members)] = True
        holding |= member
        climbing |= member
        on_branch = member[dominant]
        # as far along the limb as the seeds reach, or as the limb comes down to the hem (which the height band
        # then bounds: a leg under a skirt, an arm hanging under a poncho)
        limit = max(_quantile(_branch_arclength(means[seeds], heads, tails, parents, root), 0.98),
                    _descent(heads, tails, parents, root, axis, hem))
        along[on_branch] = _branch_arclength(means[on_branch], heads, tails, parents, root) <= limit
    band = (height >= hem) & (height <= top)
    two_chains = _two_chains(weights, ignored, min_weight)
    allowed = along & (height >= hem) & ((holding[dominant] & band) | (climbing[dominant] & two_chains))
    garment = _flood(seeds, allowed, index) & (allowed | (seeds & band))
    # rule 7: the top ring (the highest tenth of the garment's height) moves with the joint it hangs from
    garment_heights = height[garment]
    garment_top = _quantile(garment_heights, 0.98)
    ring = garment & (height >= garment_top - 0.1 * (garment_top - hem))
    ring_bottom = float(height[ring].min()) if bool(ring.any()) else garment_top
    candidates = [anchor] + [joint for joint in above if float(head_heights[joint]) <= ring_bottom]
    held = weights[ring][:, candidates].sum(dim=0)
    joint = candidates[int(held.argmax())] if bool((held > 0).any()) else anchor
    return garment, joint
