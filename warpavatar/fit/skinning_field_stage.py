"""The skinning field in a fit (TAGA's staged schedule): warm-up, frozen then trained grid, bone regularization."""

from __future__ import annotations

import torch

from warpavatar._src.precision import matmul_precision
from warpavatar.extensions.base import LossTerm
from warpavatar.model.skinning_field import VoxelSkinningField, bone_distance_prior, bone_sample_points
from warpavatar.optim import Adam, Optimizer

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
        self.optimizer = Adam(field.parameters(), lr=config.field_lr)
        self._frozen: torch.Tensor | None = None  # the grid while the field is frozen
        self._current: tuple[int, torch.Tensor] | None = None  # (step, its grid)
        # --field-cells active: the grid with a padding row [D*H*W+1, J] (evaluated whole at the last choice, the
        # chosen points rewritten every step), and the chosen grid points padded to a capacity (padding: row 0 to
        # encode, the padding row to scatter into)
        self._base: torch.Tensor | None = None
        self._encode_cells: torch.Tensor | None = None
        self._scatter_cells: torch.Tensor | None = None
        self._cell_encoding: torch.Tensor | None = None  # the MLP's input at _encode_cells, kept per choice
        self._cells_chosen = (-1, -1)  # (step, Gaussian count) of the last choice
        self.active_cells = 0

    def warmup(self, steps: int) -> float:
        """Distil the rigid bone-distance prior into the field for ``steps`` steps (each on
        ``field_warmup_batch`` grid points drawn at random, or on all); the last loss."""
        loss = torch.zeros(())
        cells = self.field.cell_count
        batch = self.config.field_warmup_batch
        generator = torch.Generator().manual_seed(self.config.seed)
        # the field's MLP alone, forward and backward: every GEMM in --matmul-precision
        with matmul_precision(self.config.matmul_precision, self.prior.device):
            for _ in range(steps):
                self.optimizer.zero_grad(set_to_none=True)
                chosen = (torch.randint(cells, (batch,), generator=generator).to(self.prior.device)
                          if 0 < batch < cells else None)
                loss = self.field.distillation_loss(self.prior, chosen)
                loss.backward()
                self.optimizer.step()
        self._frozen = self._current = None
        return float(loss.detach())

    def begin_step(self, step: int, canonical_means: torch.Tensor, *, train_field: bool) -> None:
        """Before a step's device work (outside a captured graph): with ``--field-cells active``, choose the grid
        points the step evaluates the MLP at, when the field starts training, every ``field_cells_every`` steps,
        when the number of Gaussians changed, and after :meth:`forget_cells`. A choice evaluates the whole grid
        once (no gradients) and reads the device once."""
        if self.config.field_cells != "active" or not train_field:
            return
        last_step, last_count = self._cells_chosen
        if (self._base is not None and step - last_step < self.config.field_cells_every
                and canonical_means.shape[0] == last_count):
            return
        cells = self.field.cells_read_by(torch.cat([canonical_means.detach(), self.bone_samples]), dilation=1)
        capacity = 0 if self._encode_cells is None else self._encode_cells.shape[0]
        if cells.shape[0] > capacity:  # grows by a quarter more than needed, so most choices keep the buffers
            capacity = max(cells.shape[0] + cells.shape[0] // 4, 1)
        self._use_cells(cells, capacity, (step, canonical_means.shape[0]))

    @torch.no_grad()
    def _use_cells(self, cells: torch.Tensor, capacity: int, chosen: tuple[int, int]) -> None:
        """Evaluate the whole grid (no gradients) and make ``cells`` [A] (flat indices) the active grid points,
        padded to ``capacity``; the buffers keep their storage while their sizes hold (a captured step reads
        them)."""
        field = self.field
        count, device = cells.shape[0], field.bbox_min.device
        if self._base is None or self._base.shape != (field.cell_count + 1, field.joint_count):
            self._base = torch.zeros(field.cell_count + 1, field.joint_count, device=device)
        if self._encode_cells is None or self._encode_cells.shape[0] != capacity:
            self._encode_cells = torch.zeros(capacity, dtype=torch.long, device=device)
            self._scatter_cells = torch.zeros(capacity, dtype=torch.long, device=device)
            self._cell_encoding = None
        self._base[:-1].copy_(field.grid_weights().reshape(field.cell_count, field.joint_count))
        self._encode_cells.zero_()[:count] = cells
        self._scatter_cells.fill_(field.cell_count)[:count] = cells
        # the MLP's input at the chosen points is constant until the next choice: gathered once here
        encoding = field.cell_encoding(self._encode_cells)
        if self._cell_encoding is None or self._cell_encoding.shape != encoding.shape:
            self._cell_encoding = encoding
        else:
            self._cell_encoding.copy_(encoding)
        self._cells_chosen = chosen
        self.active_cells = count
        self._current = None

    def forget_cells(self) -> None:
        """Choose the active grid points anew at the next step."""
        self._cells_chosen = (-1, -1)

    def _cells_state(self) -> dict | None:
        if self._cells_chosen[0] < 0 or self._encode_cells is None:
            return None
        return {"chosen": list(self._cells_chosen), "capacity": self._encode_cells.shape[0],
                "cells": self._encode_cells[:self.active_cells].to(torch.int32).cpu()}

    def _load_cells_state(self, state: dict | None) -> None:
        """Restore a choice of active grid points (same points, same padding: the resumed steps evaluate the MLP
        on the same rows); the grid points that no step reads are evaluated anew."""
        self.forget_cells()
        if state is None or self.config.field_cells != "active":
            return
        self._use_cells(state["cells"].to(device=self.field.bbox_min.device, dtype=torch.long),
                        int(state["capacity"]), tuple(int(v) for v in state["chosen"]))

    def log_values(self) -> dict[str, int]:
        """The number of active grid points, for the fit's log (nothing with ``--field-cells all``)."""
        return {"field_cells": self.active_cells} if self.active_cells else {}

    def graph_key(self) -> tuple:
        """What a captured step reads of this stage beyond values: the active grid points' buffers."""
        if self._encode_cells is None or self.config.field_cells != "active":
            return ()
        return (self._encode_cells.data_ptr(), self._encode_cells.shape[0], self._base.data_ptr(),
                self._cell_encoding.data_ptr())

    def grid(self, step: int, *, train_field: bool) -> torch.Tensor:
        """The skinning grid of step ``step``, evaluated once per step (with gradients when the field trains;
        while it is frozen, once for all those steps)."""
        if self._current is not None and self._current[0] == step:
            return self._current[1]
        if train_field and self.config.field_cells == "active" and self._cells_chosen[0] >= 0:
            # the chosen grid points from the MLP (with gradients), the others as evaluated at the last choice
            # (after joints were added, until the next choice: every grid point)
            values = self.field.cell_weights(self._encode_cells, encoding=self._cell_encoding)
            # written into the grid of the last choice in place, not into a copy of the whole grid: every row a
            # step reads is a chosen point's, rewritten here (detached first, should a step have kept its graph)
            grid = self._base.detach_().index_put_((self._scatter_cells,), values)[:-1]
            grid = grid.reshape(*self.field.grid_shape, self.field.joint_count)
        elif train_field:
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
        if self._base is not None:
            self._base.detach_()  # the active points' values were written into it with their graph

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

    def optimizers(self, step) -> list[Optimizer | torch.optim.Optimizer]:
        return [self.optimizer] if step.train_field else []

    def add_joints(self, parents: torch.Tensor) -> None:
        """Give the field one output per new joint (:meth:`VoxelSkinningField.add_joints`, ``parents`` [E]); its
        optimizer keeps its moments for every parameter but the replaced last layer."""
        old_parameters = list(self.field.parameters())
        self.field.add_joints(parents)
        optimizer = Adam(self.field.parameters(), lr=self.config.field_lr)
        kept = {id(parameter) for parameter in self.field.parameters()}
        for parameter in old_parameters:
            if id(parameter) in kept and parameter in self.optimizer.state:
                optimizer.state[parameter] = self.optimizer.state[parameter]
        self.optimizer = optimizer
        self._frozen = self._current = None
        self.forget_cells()

    def state_dict(self) -> dict:
        return {"field": self.field.state_dict(), "optimizer": self.optimizer.state_dict(),
                "active_cells": self._cells_state()}

    def load_state_dict(self, state: dict) -> None:
        self.field.load_state_dict(state["field"])
        self.optimizer.load_state_dict(state["optimizer"])
        self._frozen = self._current = None
        self._load_cells_state(state.get("active_cells"))
