"""TAGA's backward mapping: find and correct "ambiguous" Gaussians (TAGA, Sec. 3.2-3.4, appendix C).

Without a body template, the forward fit can skin a Gaussian to the wrong bone (armpit Gaussians that follow
the arm, Gaussians between the legs that follow the other leg) while still rendering the training view right.
Every few steps the backward mapping looks at the Gaussians posed in one training frame (observation space):

1. **Bone GMM.** Each bone gets a Gaussian component centred at its posed midpoint, one axis along the bone and
   two across it. The semi-axes are the 85th percentile of the projected distances of the points that bone
   skins with weight above ``tau = 0.2``. The GMM's normalized likelihoods are a rough, purely spatial estimate
   ``W_hat`` of the skinning weights; only the most likely bone and its skeleton neighbours (parent, children)
   keep their share (TAGA appendix C).
2. **Detection.** A Gaussian's confidence is ``S = 1 - JSD(W_hat || W)`` (Jensen-Shannon divergence in bits,
   so ``S`` lies in [0, 1]); ``S <= alpha`` marks it ambiguous. A few EM rounds refit the semi-axes and
   mixture weights on the normal Gaussians only, until the ambiguous set stops changing.
3. **Correction.** An ambiguous Gaussian takes the weights of the one among its K nearest normal neighbours
   (observation space, from :func:`warpavatar.ops.knn_graph`) whose weights agree best with its own ``W_hat``.
4. **Inverse LBS.** With the corrected weights ``W'``, its observed position maps back to a corrected
   canonical position ``p* = (sum_k W'_k B_k)^-1 p_o`` (:func:`warpavatar.ops.inverse_lbs`). A correction
   that would move the Gaussian far (``max_move``; not in TAGA) is dropped: it comes from a frame where
   distant parts touch (a hand on the head), where a spatial estimate cannot tell them apart.

The result is cached and used as soft constraints until the next refresh (the cycle losses): the canonical
Gaussian is pulled towards ``p*`` (``L_geo``, mean L1 distance) and the skinning field at ``p*`` towards ``W'``
(``L_skin``, mean squared difference). Both apply to the ambiguous Gaussians only.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from warpavatar import ops
from warpavatar.extensions.base import Extension, LossTerm, option

__all__ = ["jensen_shannon", "bone_axes", "BoneGMM", "BackwardMapping", "BackwardMappingOptions",
           "BackwardMappingExtension"]


def jensen_shannon(p: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """Jensen-Shannon divergence [N] in bits (0..1) between the rows of two distributions [N,J]."""
    middle = 0.5 * (p + q)
    tiny = torch.finfo(p.dtype).tiny

    def kl(a, b):
        # 0 * log 0 counts as 0; b >= a/2 > 0 wherever a > 0
        return torch.where(a > 0, a * (torch.log2(a.clamp_min(tiny)) - torch.log2(b.clamp_min(tiny))),
                           torch.zeros_like(a)).sum(-1)

    return (0.5 * kl(p, middle) + 0.5 * kl(q, middle)).clamp(0.0, 1.0)


def bone_axes(heads: torch.Tensor, tails: torch.Tensor) -> torch.Tensor:
    """Orthonormal frames [J,3,3] of bones head->tail ([J,3] each): row 0 along the bone, rows 1-2 across it.

    A bone of zero length takes the z axis as its direction.
    """
    along = tails - heads
    length = along.norm(dim=-1, keepdim=True)
    z_axis = torch.tensor([0.0, 0.0, 1.0], device=heads.device, dtype=heads.dtype).expand_as(along)
    along = torch.where(length > 1e-9, along / length.clamp_min(1e-9), z_axis)
    # the world axis least aligned with the bone completes the basis
    helper = torch.eye(3, device=heads.device, dtype=heads.dtype)[along.abs().argmin(dim=-1)]
    across = torch.linalg.cross(along, helper)
    across = across / across.norm(dim=-1, keepdim=True)
    third = torch.linalg.cross(along, across)
    return torch.stack([along, across, third], dim=1)


class BoneGMM:
    """One Gaussian component per bone, in one posed frame (TAGA Sec. 3.2).

    Args:
        heads: [J,3] posed bone heads (world units).
        tails: [J,3] posed bone tails.
        parents: [J] parent index of each bone (-1 for the root).
        min_semi_axis: floor of every semi-axis (world units), so a bone with few points stays a proper density.
    """

    def __init__(self, heads: torch.Tensor, tails: torch.Tensor, parents: torch.Tensor, *, min_semi_axis: float):
        joint_count = heads.shape[0]
        self.centres = 0.5 * (heads + tails)  # [J,3]
        self.axes = bone_axes(heads, tails)  # [J,3,3]
        self.min_semi_axis = float(min_semi_axis)
        length = (tails - heads).norm(dim=-1).clamp_min(self.min_semi_axis)
        # until points are assigned: half the bone along it, a quarter of it across
        self.semi_axes = torch.stack([0.5 * length, 0.25 * length, 0.25 * length], dim=-1).clamp_min(
            self.min_semi_axis)
        self.log_mix = torch.full((joint_count,), -float(torch.log(torch.tensor(float(joint_count)))),
                                  device=heads.device)
        # bone j and its skeleton neighbours: itself, its parent, its children
        neighbours = torch.eye(joint_count, dtype=torch.bool, device=heads.device)
        bones = torch.arange(joint_count, device=heads.device)
        has_parent = parents >= 0
        neighbours[bones[has_parent], parents[has_parent].long()] = True
        neighbours[parents[has_parent].long(), bones[has_parent]] = True
        self.neighbours = neighbours

    def local(self, points: torch.Tensor) -> torch.Tensor:
        """Coordinates [N,J,3] of points [N,3] in every bone's frame (along, across, across)."""
        return torch.einsum("jab,njb->nja", self.axes, points[:, None, :] - self.centres[None])

    def estimate(self, points: torch.Tensor) -> torch.Tensor:
        """Spatial skinning estimate W_hat [N,J]: component likelihoods normalized over the most likely bone
        and its skeleton neighbours (other bones get 0)."""
        scaled = self.local(points) / self.semi_axes[None]
        log_density = -0.5 * (scaled * scaled).sum(-1) - torch.log(self.semi_axes).sum(-1)[None] + self.log_mix[None]
        keep = self.neighbours[log_density.argmax(dim=-1)]  # [N,J]
        log_density = log_density.masked_fill(~keep, float("-inf"))
        return torch.softmax(log_density, dim=-1)

    def fit(self, points: torch.Tensor, weights: torch.Tensor, *, use: torch.Tensor, weight_floor: float,
            percentile: float) -> None:
        """M-step: semi-axes from the ``use``d points that each bone skins above ``weight_floor``.

        A bone with fewer than 4 such points keeps its previous semi-axes. Mixture weights are the bones' shares
        of the ``use``d skinning weight.
        """
        local = self.local(points).abs()  # [N,J,3]
        semi = self.semi_axes.clone()
        for bone in range(self.centres.shape[0]):
            member = use & (weights[:, bone] > weight_floor)
            if int(member.sum()) >= 4:
                semi[bone] = torch.quantile(local[member, bone], percentile, dim=0)
        self.semi_axes = semi.clamp_min(self.min_semi_axis)
        share = weights[use].sum(0) if bool(use.any()) else weights.sum(0)
        share = share / share.sum().clamp_min(1e-12)
        self.log_mix = torch.log(share.clamp_min(1e-4))


class BackwardMapping:
    """Detection and correction of ambiguous Gaussians, and the cycle losses they feed (TAGA Sec. 3.2-3.4).

    Args:
        heads: [J,3] rest-pose bone heads (world units).
        tails: [J,3] rest-pose bone tails.
        parents: [J] parent index of each bone (-1 for the root).
        threshold: ``alpha``: Gaussians whose confidence ``1 - JSD`` is at most this are ambiguous.
        weight_floor: ``tau``: a bone's GMM component is fitted to the points it skins above this weight.
        percentile: quantile of the projected distances taken as a semi-axis (TAGA: 0.85).
        neighbours: K nearest normal Gaussians an ambiguous one may take its weights from.
        em_iterations: most EM rounds per refresh.
        min_semi_axis: floor of the GMM semi-axes (world units).
        max_move: corrections that would move a canonical centre farther than this (world units) are dropped:
            they come from frames where distant parts touch, where a purely spatial GMM cannot be trusted.
            ``None``: keep all.
    """

    def __init__(self, heads: torch.Tensor, tails: torch.Tensor, parents: torch.Tensor, *, threshold: float = 0.5,
                 weight_floor: float = 0.2, percentile: float = 0.85, neighbours: int = 8, em_iterations: int = 5,
                 min_semi_axis: float = 0.005, max_move: float | None = None):
        if not 0.0 < threshold < 1.0:
            raise ValueError(f"threshold must lie in (0, 1), got {threshold}")
        if not 1 <= neighbours <= 32:
            raise ValueError(f"neighbours must be in [1, 32], got {neighbours}")
        self.heads = heads.float()
        self.tails = tails.float()
        self.parents = parents.long()
        self.threshold = float(threshold)
        self.weight_floor = float(weight_floor)
        self.percentile = float(percentile)
        self.neighbours = int(neighbours)
        self.em_iterations = int(em_iterations)
        self.min_semi_axis = float(min_semi_axis)
        self.max_move = None if max_move is None else float(max_move)
        #: the cached correction: Gaussian indices [A], corrected canonical positions [A,3], weights [A,J]
        self.index: torch.Tensor | None = None
        self.target_means: torch.Tensor | None = None
        self.target_weights: torch.Tensor | None = None

    # ---------------------------------------------------------------------------------------------- detect
    def posed_gmm(self, bone_transforms: torch.Tensor) -> BoneGMM:
        """The bone GMM of a pose [J,4,4], before any EM round."""
        rotation, translation = bone_transforms[:, :3, :3], bone_transforms[:, :3, 3]
        heads = torch.einsum("jab,jb->ja", rotation, self.heads) + translation
        tails = torch.einsum("jab,jb->ja", rotation, self.tails) + translation
        return BoneGMM(heads, tails, self.parents, min_semi_axis=self.min_semi_axis)

    def detect(self, posed_means: torch.Tensor, weights: torch.Tensor, bone_transforms: torch.Tensor
               ) -> tuple[torch.Tensor, torch.Tensor]:
        """Ambiguous Gaussians of one posed frame.

        Args:
            posed_means: [N,3] observation-space Gaussian centres.
            weights: [N,J] their current skinning weights.
            bone_transforms: [J,4,4] the frame's bone transforms.

        Returns:
            ``(ambiguous [N] bool, W_hat [N,J])`` from the last EM round.
        """
        gmm = self.posed_gmm(bone_transforms)
        use = torch.ones(posed_means.shape[0], dtype=torch.bool, device=posed_means.device)
        gmm.fit(posed_means, weights, use=use, weight_floor=self.weight_floor, percentile=self.percentile)
        ambiguous = ~use
        for _ in range(max(1, self.em_iterations)):
            estimate = gmm.estimate(posed_means)  # E-step
            found = (1.0 - jensen_shannon(estimate, weights)) <= self.threshold
            if torch.equal(found, ambiguous):
                break
            ambiguous = found
            gmm.fit(posed_means, weights, use=~ambiguous, weight_floor=self.weight_floor,
                    percentile=self.percentile)  # M-step on the normal Gaussians
        return ambiguous, estimate

    # --------------------------------------------------------------------------------------------- correct
    def correct(self, posed_means: torch.Tensor, weights: torch.Tensor, ambiguous: torch.Tensor,
                estimate: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """New weights for ambiguous Gaussians from their nearest normal neighbours (TAGA Eq. 6).

        Returns:
            ``(index [A], weights [A,J])``: the ambiguous Gaussians that had a normal neighbour among their
            ``4 * neighbours`` nearest, and the weights of the best of their first K normal neighbours.
        """
        candidates = torch.nonzero(ambiguous).squeeze(1)
        if candidates.numel() == 0 or bool(ambiguous.all()):
            return candidates, weights[candidates]
        search = min(4 * self.neighbours, posed_means.shape[0] - 1)
        graph, _ = ops.knn_graph(posed_means, search)
        rows = graph[candidates]  # [A,search]
        valid = rows >= 0
        normal = valid & ~ambiguous[rows.clamp_min(0)]
        # only the first K normal neighbours (nearest first) compete
        normal &= torch.cumsum(normal.int(), dim=1) <= self.neighbours
        score = 1.0 - jensen_shannon(estimate[candidates][:, None, :].expand(-1, rows.shape[1], -1),
                                     weights[rows.clamp_min(0)])
        score = score.masked_fill(~normal, -1.0)
        best_score, best = score.max(dim=1)
        found = best_score >= 0.0
        chosen = rows.gather(1, best[:, None]).squeeze(1)
        return candidates[found], weights[chosen[found]]

    # ------------------------------------------------------------------------------------------- refresh
    @torch.no_grad()
    def refresh(self, canonical_means: torch.Tensor, posed_means: torch.Tensor, weights: torch.Tensor,
                bone_transforms: torch.Tensor) -> int:
        """Detect and correct on one posed frame and cache the soft constraints.

        Args:
            canonical_means: [N,3] the canonical Gaussian centres the constraints will pull.
            posed_means: [N,3] the same Gaussians posed in the frame (everything before skinning included).
            weights: [N,J] the skinning weights that posed them.
            bone_transforms: [J,4,4] the frame's bone transforms.

        Returns:
            the number of Gaussians corrected.
        """
        ambiguous, estimate = self.detect(posed_means, weights, bone_transforms)
        index, corrected = self.correct(posed_means, weights, ambiguous, estimate)
        posed = posed_means[index]
        # inverse LBS with the old weights gives back exactly what was skinned; its offset from the canonical
        # centre (a pose correction or secondary displacement applied before skinning) is kept
        skinned_from, _ = ops.inverse_lbs(posed.contiguous(), weights[index].contiguous(), bone_transforms)
        corrected_at, _ = ops.inverse_lbs(posed.contiguous(), corrected.contiguous(), bone_transforms)
        target = corrected_at - (skinned_from - canonical_means[index])
        keep = torch.isfinite(target).all(dim=-1)
        if self.max_move is not None:
            keep &= (target - canonical_means[index]).norm(dim=-1) <= self.max_move
        self.index = index[keep]
        self.target_means = target[keep]
        self.target_weights = corrected[keep]
        return int(self.index.numel())

    def clear(self) -> None:
        """Forget the cached constraints (the Gaussians were added, removed or reordered)."""
        self.index = self.target_means = self.target_weights = None

    @property
    def ready(self) -> bool:
        return self.index is not None

    # -------------------------------------------------------------------------------------------- losses
    def losses(self, canonical_means: torch.Tensor, field, grid: torch.Tensor | None = None
               ) -> tuple[torch.Tensor, torch.Tensor]:
        """The cycle losses ``(L_geo, L_skin)`` of the cached constraints (zeros when none are cached).

        ``L_geo``: mean L1 distance of the ambiguous canonical centres from their corrected positions.
        ``L_skin``: mean squared difference of the field's weights at the corrected positions from the
        corrected weights.
        """
        zero = canonical_means.sum() * 0.0
        if self.index is None or self.index.numel() == 0:
            return zero, zero
        geo = (canonical_means[self.index] - self.target_means).abs().sum(-1).mean()
        skin = ((field.weights(self.target_means, grid) - self.target_weights) ** 2).sum(-1).mean()
        return geo, skin

    # ------------------------------------------------------------------------------------------ files
    def state(self) -> dict | None:
        if self.index is None:
            return None
        return {"index": self.index.cpu(), "target_means": self.target_means.cpu(),
                "target_weights": self.target_weights.cpu()}

    def load_state(self, state: dict | None, *, device) -> None:
        if state is None:
            self.clear()
            return
        self.index = state["index"].to(device)
        self.target_means = state["target_means"].to(device)
        self.target_weights = state["target_weights"].to(device)


@dataclass
class BackwardMappingOptions:
    backward_from: int = option(3000, "first step of the backward-mapping phase")
    backward_until: int = option(6500, "last step of the backward-mapping phase")
    backward_every: int = option(150, "steps between refreshes of the detected and corrected Gaussians")
    backward_threshold: float = option(0.5, "Gaussians whose confidence 1 - JSD(GMM weights, weights) is at most "
                                       "this are ambiguous")
    backward_neighbours: int = option(8, "nearest normal Gaussians an ambiguous one may take its weights from")
    backward_max_move: float = option(0.05, "corrections moving a canonical centre farther than this fraction of "
                                      "the canonical extent are dropped (distant parts touching in the frame)")
    lambda_geo: float = option(1000.0, "weight of the geometry cycle loss (mean L1 distance, world units)")
    lambda_skin: float = option(10.0, "weight of the skinning cycle loss (mean squared weight difference)")

    def __post_init__(self):
        if not 0.0 < self.backward_threshold < 1.0:
            raise ValueError(f"backward_threshold must lie in (0, 1), got {self.backward_threshold}")
        if self.backward_every < 1:
            raise ValueError(f"backward_every must be at least 1, got {self.backward_every}")


class BackwardMappingExtension(Extension):
    """Runs :class:`BackwardMapping` between ``backward_from`` and ``backward_until`` while the field trains:
    every ``backward_every`` steps it re-detects and corrects on the step's training frame, and every step adds
    the cycle losses of the cached corrections."""

    name = "backward_mapping"
    title = "TAGA's backward mapping (--backward-mapping)"
    summary = ("detect Gaussians whose skinning disagrees with a bone GMM (ambiguous), correct them from their "
               "nearest normal neighbours and pull the canonical model and skinning field towards the correction "
               "(TAGA's cycle losses)")
    options_type = BackwardMappingOptions
    presets = {"quick": {"backward_from": 1000, "backward_until": 1700}}

    def attach(self) -> None:
        fit, options = self.fit, self.options
        skeleton = fit.frames.skeleton
        device = fit.device
        self.mapping = BackwardMapping(
            torch.as_tensor(skeleton.heads, dtype=torch.float32, device=device),
            torch.as_tensor(skeleton.tails, dtype=torch.float32, device=device),
            torch.as_tensor(skeleton.parents, device=device), threshold=options.backward_threshold,
            neighbours=options.backward_neighbours, min_semi_axis=0.005 * fit.extent,
            max_move=options.backward_max_move * fit.extent)
        self.refreshed = -1  # step of the last refresh

    def _active(self, step) -> bool:
        return step.train_field and self.options.backward_from <= step.step <= self.options.backward_until

    def losses(self, step) -> dict[str, LossTerm]:
        if not self._active(step):
            return {}
        mapping, avatar = self.mapping, self.fit.avatar
        if not mapping.ready or step.step - self.refreshed >= self.options.backward_every:
            bones = self.fit.frames.bone_transforms[step.index]
            with torch.no_grad():
                posed = avatar.pose(bones, grid=step.grid)
                mapping.refresh(avatar.gaussians.means.detach(), posed["means"], posed["weights"],
                                avatar.pose_bones(bones))
            self.refreshed = step.step
        geo, skin = mapping.losses(avatar.gaussians.means, self.fit.skinning.field, step.grid)
        return {"geo": LossTerm(self.options.lambda_geo, geo), "skin": LossTerm(self.options.lambda_skin, skin)}

    def on_gaussians_renumbered(self, source_index: torch.Tensor) -> None:
        self.mapping.clear()  # its cached indices no longer name the same Gaussians

    def log_values(self) -> dict[str, float]:
        # ambiguous Gaussians the backward mapping has corrected (its cached constraints)
        return {"ambiguous": int(self.mapping.index.numel()) if self.mapping.ready else 0}

    def state_dict(self) -> dict:
        return {"mapping": self.mapping.state(), "refreshed": self.refreshed}

    def load_state_dict(self, state: dict) -> None:
        self.mapping.load_state(state["mapping"], device=self.fit.device)
        self.refreshed = int(state["refreshed"])
