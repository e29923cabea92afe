"""The skinning field in a fit (TAGA's staged schedule): warm-up, frozen then trained grid, bone regularization."""

from __future__ import annotations

import torch

from warpavatar._src.cuda_graph import adam_options
from warpavatar.extensions.base import LossTerm
from warpavatar.model.skinning_field import VoxelSkinningField, bone_distance_prior, bone_sample_points

__all__ = ["SkinningStage"]


class SkinningStage:
    """Trains the avatar's skinning field: TAGA appendix C's warm-up distils a rigid bone-distance prior, then the
    field stays frozen while the Gaussians alone train (``gaussian_only_steps``), then it trains too under the
    bone regularization.

    Args:
        field: the avatar's skinning field.
        skeleton: the rest skeleton (its bones give the prior and the regularization samples).
        config: the fit configuration (``skinning_prior_temperature``, ``field_lr``, ``lambda_bone``).
        extent: the canonical box's half-diagonal [world units] (the prior's temperature is relative to it).
    """

    def __init__(self, field: VoxelSkinningField, skeleton, config, *, extent: float):
        self.field = field
        self.config = config
        device = field.bbox_min.device
        heads = torch.as_tensor(skeleton.heads, dtype=torch.float32, device=device)
        tails = torch.as_tensor(skeleton.tails, dtype=torch.float32, device=device)
        parents = torch.as_tensor(skeleton.parents, device=device)
        self.bone_samples, self.bone_sample_index = bone_sample_points(heads, tails, parents)
        #: the warm-up's target [D*H*W, J]: the rigid bone-distance prior at every grid point
        self.prior = bone_distance_prior(field.grid_points.reshape(-1, 3), heads, tails,
                                         temperature=config.skinning_prior_temperature * extent)
        self.optimizer = torch.optim.Adam(field.parameters(), lr=config.field_lr, **adam_options(device))
        self._frozen: torch.Tensor | None = None  # the grid while the field is frozen
        self._current: tuple[int, torch.Tensor] | None = None  # (step, its grid)

    def warmup(self, steps: int) -> float:
        """Distil the rigid bone-distance prior into the field for ``steps`` steps; the last loss."""
        loss = torch.zeros(())
        for _ in range(steps):
            self.optimizer.zero_grad(set_to_none=True)
            loss = self.field.distillation_loss(self.prior)
            loss.backward()
            self.optimizer.step()
        self._frozen = self._current = None
        return float(loss.detach())

    def grid(self, step: int, *, train_field: bool) -> torch.Tensor:
        """The skinning grid of step ``step``, evaluated once per step (with gradients when the field trains;
        while it is frozen, once for all those steps)."""
        if self._current is not None and self._current[0] == step:
            return self._current[1]
        if train_field:
            grid = self.field.grid_weights()
        else:
            if self._frozen is None:
                with torch.no_grad():
                    self._frozen = self.field.grid_weights()
            grid = self._frozen
        self._current = (step, grid)
        return grid

    def release_graph(self) -> None:
        """Keep this step's grid values but drop its autograd graph (after the backward pass): a graph that
        outlives its step keeps the field parameters' AccumulateGrad nodes, bound to the stream that made them,
        and a step captured on another stream would synchronize with that one (an invalid capture)."""
        if self._current is not None and self._current[1].requires_grad:
            self._current = (self._current[0], self._current[1].detach())

    def forget_step(self) -> None:
        """Evaluate the grid anew at the next :meth:`grid` call, even for the same step (capturing a step that
        just ran eagerly)."""
        self._current = None

    def losses(self, step, groups: torch.Tensor | None) -> dict[str, LossTerm]:
        """TAGA's bone regularization while the field trains (``groups``: see
        :meth:`~warpavatar.model.skinning_field.VoxelSkinningField.bone_loss`)."""
        if not step.train_field:
            return {}
        bone = self.field.bone_loss(self.bone_samples, self.bone_sample_index, step.grid, groups=groups)
        return {"bone": LossTerm(self.config.lambda_bone, bone)}

    def optimizers(self, step) -> list[torch.optim.Optimizer]:
        return [self.optimizer] if step.train_field else []

    def add_joints(self, parents: torch.Tensor) -> None:
        """Give the field one output per new joint (:meth:`VoxelSkinningField.add_joints`, ``parents`` [E]); its
        optimizer keeps its moments for every parameter but the replaced last layer."""
        old_parameters = list(self.field.parameters())
        self.field.add_joints(parents)
        optimizer = torch.optim.Adam(self.field.parameters(), lr=self.config.field_lr,
                                     **adam_options(self.field.bbox_min.device))
        kept = {id(parameter) for parameter in self.field.parameters()}
        for parameter in old_parameters:
            if id(parameter) in kept and parameter in self.optimizer.state:
                optimizer.state[parameter] = self.optimizer.state[parameter]
        self.optimizer = optimizer
        self._frozen = self._current = None

    def state_dict(self) -> dict:
        return {"field": self.field.state_dict(), "optimizer": self.optimizer.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        self.field.load_state_dict(state["field"])
        self.optimizer.load_state_dict(state["optimizer"])
        self._frozen = self._current = None
