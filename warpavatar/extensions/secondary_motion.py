"""Secondary motion of the training instants on SMAD's Gaussian graph (SMAD, Sec. 3.2-3.3).

Loose cloth (a skirt that flares and swings) does not follow the skeleton: its shape at an instant depends on
the motion before it. On SMAD's graph (:mod:`warpavatar.extensions.graph`), every training frame ``t`` has a
learned displacement of every node, ``D[t] [M,3]`` in the canonical (rest) frame.

The displacements are what SMAD's dynamics produce, recovered here by inverse rendering, frame by frame, and
regularized as SMAD regularizes its simulation (Eq. 11): the displaced graph keeps its edge lengths
(:func:`warpavatar.ops.isometry_loss`) and the node velocities stay small
(:func:`warpavatar.ops.damping_loss` on the finite-difference velocity of the displacement sequence).

A pose equal to a training frame's (a novel view of a training instant, or a replay of the training motion)
gets that frame's displacement; any other pose gets none (the skinned, pose-corrected shape).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from warpavatar import ops
from warpavatar.extensions.base import Extension, LossTerm, option
from warpavatar.extensions.graph import GRAPH_PRESETS, GraphMotionOptions, NodeGraph, graph_nodes
from warpavatar.geometry import match_pose
from warpavatar.optim import Optimizer

__all__ = ["SecondaryMotion", "SecondaryMotionOptions", "SecondaryMotionExtension"]


class SecondaryMotion(NodeGraph):
    """Per-training-frame node displacements on a voxel-downsampled Gaussian graph.

    Args:
        node_positions: [M,3] canonical node positions [world units] (see :func:`voxel_downsample`).
        frame_poses: [T,J,4,4] bone transforms of the training frames, in the order of the displacements.
        voxel_size: the voxel edge the nodes were made with [world units]; it sets the kernel width of the
            Gaussian-to-node binding and the unit of the regularizers.
        neighbors: k of the node graph's k-NN edges (SMAD: 16).
        bind_count: nearest nodes each Gaussian blends.

    Velocities in the regularizers are in voxels per training frame (finite differences of consecutive rows).
    """

    name = "secondary_motion"

    def __init__(self, node_positions: torch.Tensor, frame_poses: torch.Tensor, *, voxel_size: float,
                 neighbors: int = 16, bind_count: int = 4):
        super().__init__(node_positions, voxel_size=voxel_size, neighbors=neighbors, bind_count=bind_count)
        self.register_buffer("frame_poses", frame_poses.detach().float().clone())
        self.displacement = torch.nn.Parameter(torch.zeros(frame_poses.shape[0], self.node_count, 3,
                                                           device=self.nodes.device))

    @property
    def frame_count(self) -> int:
        return self.displacement.shape[0]

    # --------------------------------------------------------------------------------------- frames
    def frame_match(self, bone_transforms: torch.Tensor, *, tolerance: float = 1e-4
                    ) -> tuple[torch.Tensor, torch.Tensor]:
        """(index of the training frame whose pose equals ``bone_transforms``, 1.0 if it matches else 0.0).

        Both are device tensors: no host synchronization.
        """
        return match_pose(self.frame_poses, bone_transforms, tolerance=tolerance)

    def node_displacement(self, bone_transforms: torch.Tensor) -> torch.Tensor:
        """Canonical displacement [M,3] of every node for this pose (zeros unless it is a training instant)."""
        best, matched = self.frame_match(bone_transforms)
        return self.displacement[best] * matched

    def damping(self, frame: torch.Tensor | int) -> torch.Tensor:
        """SMAD's damping term around training frame ``frame``: mean squared node velocity over the (up to two)
        finite differences that involve it, in voxels per frame.

        Only rows ``frame - 1 .. frame + 1`` get a gradient, so a row-sparse optimizer touches only them.
        """
        frame = int(frame)
        low, high = max(0, frame - 1), min(self.frame_count - 1, frame + 1)
        if high <= low:
            return self.displacement.sum() * 0.0
        window = self.displacement[low: high + 1]
        velocity = (window[1:] - window[:-1]) / self.hyper["voxel_size"]
        return ops.damping_loss(velocity.contiguous())

    def magnitude(self, frame: torch.Tensor | int) -> torch.Tensor:
        """Mean squared displacement of frame ``frame``'s nodes, in voxels (keeps what the images leave free at
        rest)."""
        return (self.displacement[int(frame)] / self.hyper["voxel_size"]).square().sum(-1).mean()

    def sparsify_gradient(self) -> None:
        """Turn the displacement's dense gradient into a row-sparse one (the frames this step touched), for
        :class:`torch.optim.SparseAdam`: rows of frames not seen in a step then keep still, where a dense Adam
        would keep moving them on stale momentum."""
        grad = self.displacement.grad
        if grad is not None and not grad.is_sparse:
            rows = torch.nonzero(grad.abs().amax(dim=(1, 2)) > 0).squeeze(1)
            self.displacement.grad = torch.sparse_coo_tensor(rows[None], grad[rows], grad.shape).coalesce()

    @classmethod
    def from_file_state(cls, state: dict, *, device="cpu") -> "SecondaryMotion":
        weights = state["state_dict"]
        module = cls.__new__(cls)
        torch.nn.Module.__init__(module)
        module.hyper = dict(state["hyper"])
        for name in ("nodes", "edges", "rest_offset", "frame_poses"):
            module.register_buffer(name, weights[name].to(device))
        module.displacement = torch.nn.Parameter(weights["displacement"].to(device))
        module.restore_binding(state.get("binding"), device=device)
        return module

    def extra_repr(self) -> str:
        return (f"nodes={self.node_count}, edges={self.edges.shape[0]}, frames={self.frame_count}, "
                f"voxel_size={self.hyper['voxel_size']:.4g}")


@dataclass
class SecondaryMotionOptions(GraphMotionOptions):
    lr_secondary: float = option(1e-4, "Adam learning rate of the node displacements, times the canonical extent")


class SecondaryMotionExtension(Extension):
    """Per-training-frame node displacements, from ``secondary_from`` on, with a row-sparse Adam."""

    name = "secondary_motion"
    title = "secondary motion on SMAD's graph (--secondary-motion or --dynamics)"
    summary = ("learn per-training-frame displacements of a voxel-downsampled Gaussian graph (cloth that swings; "
               "novel views of training instants and replays use them)")
    options_type = SecondaryMotionOptions
    presets = GRAPH_PRESETS
    conflicts = {"dynamics": "choose one secondary-motion model: --secondary-motion (per-frame displacements) or "
                             "--dynamics (learned dynamics), not both"}
    part: SecondaryMotion | None = None

    def _build(self, part: SecondaryMotion) -> None:
        self.part = self.fit.avatar.add_part(part)
        # row-sparse Adam: a frame's displacements move only in the steps that see that frame
        self.optimizer = torch.optim.SparseAdam([part.displacement], lr=self.options.lr_secondary * self.fit.extent)

    def begin_step(self, step) -> None:
        if self.part is None and step.step >= self.options.secondary_from:
            nodes, voxel = graph_nodes(self.fit, self.options)
            part = SecondaryMotion(nodes, self.fit.frames.bone_transforms, voxel_size=voxel)
            part.bind(self.fit.avatar.gaussians.means)
            self._build(part)

    def losses(self, step) -> dict[str, LossTerm]:
        if self.part is None:
            return {}
        options, part = self.options, self.part
        return {"isometry": LossTerm(options.lambda_isometry, part.isometry(part.displacement[step.index])),
                "damping": LossTerm(options.lambda_damping, part.damping(step.index)),
                "displacement": LossTerm(options.lambda_displacement, part.magnitude(step.index))}

    def optimizers(self, step) -> list[Optimizer | torch.optim.Optimizer]:
        return [] if self.part is None else [self.optimizer]

    def after_backward(self, step) -> None:
        if self.part is not None:
            self.part.sparsify_gradient()

    def on_gaussians_renumbered(self, source_index: torch.Tensor) -> None:
        if self.part is not None:
            self.part.bind(self.fit.avatar.gaussians.means)

    def state_dict(self) -> dict:
        if self.part is None:
            return {}
        return {"part": self.part.state_for_file(), "optimizer": self.optimizer.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        if state:
            self._build(SecondaryMotion.from_file_state(state["part"], device=self.fit.device))
            self.optimizer.load_state_dict(state["optimizer"])
