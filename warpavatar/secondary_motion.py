"""Secondary motion of the training instants on SMAD's Gaussian graph (paper 000, Sec. 3.2-3.3).

Loose cloth (a skirt that flares and swings) does not follow the skeleton: its shape at an instant depends on
the motion before it. Following SMAD, the canonical Gaussians are voxel-downsampled into graph *nodes*, joined
by k-NN edges (k = 16) whose rest offsets are those of the canonical shape. Every training frame ``t`` has a
learned displacement of every node, ``D[t] [M,3]`` in the canonical (rest) frame; a Gaussian moves by the
Gaussian-kernel blend of the displacements of its nearest nodes, before linear blend skinning (so the
displacement turns with the body: skinning maps it through the blended bone transform).

The displacements are what SMAD's dynamics produce, recovered here by inverse rendering, frame by frame, and
regularized as SMAD regularizes its simulation (Eq. 11): the displaced graph keeps its edge lengths
(:func:`warpavatar.ops.isometry_loss`) and the node velocities stay small
(:func:`warpavatar.ops.damping_loss` on the finite-difference velocity of the displacement sequence).

A pose equal to a training frame's (a novel view of a training instant, or a replay of the training motion)
gets that frame's displacement; any other pose gets none (the skinned, pose-corrected shape).
"""

from __future__ import annotations

import warnings

import torch

from warpavatar import ops

__all__ = ["NodeGraph", "SecondaryMotion", "voxel_downsample", "match_pose"]


class _BlendNodes(torch.autograd.Function):
    """``out = W @ values`` for a sparse row-blend matrix W [N,M], with ``W^T`` stored for the backward.

    On the CPU a sparse CSR product computes each output row on its own, so forward and backward are
    deterministic (the backward of a plain ``values[index]`` gather accumulates with threads, in varying order,
    there). On CUDA the product may differ in the last bits between runs, as the rasterizer's atomics do.
    """

    @staticmethod
    def forward(ctx, values, blend, blend_transposed):
        ctx.blend_transposed = blend_transposed
        return torch.sparse.mm(blend, values)

    @staticmethod
    def backward(ctx, grad_out):
        return torch.sparse.mm(ctx.blend_transposed, grad_out.contiguous()), None, None


def _blend_matrices(index: torch.Tensor, weights: torch.Tensor, node_count: int
                    ) -> tuple[torch.Tensor, torch.Tensor]:
    rows = torch.arange(index.shape[0], device=index.device)[:, None].expand_as(index).reshape(-1)
    columns = index.reshape(-1)
    values = weights.reshape(-1).float()
    shape = (index.shape[0], node_count)
    with warnings.catch_warnings():  # torch flags its sparse CSR support as beta
        warnings.simplefilter("ignore", UserWarning)
        blend = torch.sparse_coo_tensor(torch.stack([rows, columns]), values, shape).coalesce().to_sparse_csr()
        transposed = torch.sparse_coo_tensor(torch.stack([columns, rows]), values,
                                             shape[::-1]).coalesce().to_sparse_csr()
    return blend, transposed


def match_pose(frame_poses: torch.Tensor, bone_transforms: torch.Tensor, *, tolerance: float = 1e-4
               ) -> tuple[torch.Tensor, torch.Tensor]:
    """(index of the row of ``frame_poses`` [T,J,4,4] closest to ``bone_transforms`` [J',4,4] (J' >= J), 1.0 if
    every entry is within ``tolerance`` else 0.0), both device tensors: no host synchronization.

    ``T`` must be at least 1.
    """
    difference = (frame_poses - bone_transforms[: frame_poses.shape[1]]).abs().amax(dim=(1, 2, 3))
    best = torch.argmin(difference)
    return best, (difference[best] <= tolerance).to(frame_poses.dtype)


def voxel_downsample(points: torch.Tensor, voxel_size: float) -> torch.Tensor:
    """Mean of the points in each occupied voxel of edge ``voxel_size`` [world units]: [M,3], M <= N.

    The result is ordered by voxel key, so it does not depend on the order of ``points``'s rows up to float
    summation order.
    """
    if points.shape[0] == 0:
        return points.new_zeros((0, 3))
    cells = torch.floor((points - points.min(0).values) / voxel_size).long()
    span = cells.max(0).values + 1
    keys = (cells[:, 0] * span[1] + cells[:, 1]) * span[2] + cells[:, 2]
    unique, inverse = torch.unique(keys, return_inverse=True)
    sums = torch.zeros(unique.shape[0], 3, dtype=points.dtype, device=points.device).index_add_(0, inverse, points)
    counts = torch.zeros(unique.shape[0], dtype=points.dtype, device=points.device).index_add_(
        0, inverse, torch.ones_like(points[:, 0]))
    return sums / counts[:, None]


class NodeGraph(torch.nn.Module):
    """SMAD's Gaussian graph: voxel-downsampled nodes, their k-NN edges and the Gaussians' binding to them.

    The base of the two secondary-motion models (:class:`SecondaryMotion`, per-frame displacements, and
    :class:`warpavatar.dynamics.SecondaryDynamics`, learned dynamics): a model gives node displacements [M,3]
    in the canonical frame, the graph blends them onto the Gaussians and measures their stretch.

    Args:
        node_positions: [M,3] canonical node positions [world units] (see :func:`voxel_downsample`).
        voxel_size: the voxel edge the nodes were made with [world units]; it sets the kernel width of the
            Gaussian-to-node binding and the unit of the regularizers.
        neighbors: k of the node graph's k-NN edges (SMAD: 16).
        bind_count: nearest nodes each Gaussian blends.
    """

    def __init__(self, node_positions: torch.Tensor, *, voxel_size: float, neighbors: int = 16, bind_count: int = 4):
        super().__init__()
        node_positions = node_positions.detach().float().contiguous()
        node_count = node_positions.shape[0]
        if node_count < 2:
            raise ValueError(f"secondary motion needs at least 2 graph nodes, got {node_count}")
        self.hyper = dict(voxel_size=float(voxel_size), neighbors=int(neighbors), bind_count=int(bind_count))
        self.register_buffer("nodes", node_positions.clone())
        index, _ = ops.knn_graph(node_positions, min(neighbors, node_count - 1))
        receivers = torch.arange(node_count, device=index.device)[:, None].expand_as(index)
        valid = index >= 0
        edges = torch.stack([receivers[valid], index[valid]], dim=1).to(torch.int32).contiguous()
        self.register_buffer("edges", edges)
        self.register_buffer("rest_offset", (node_positions[edges[:, 0].long()] - node_positions[edges[:, 1].long()]))
        self._binding: tuple[torch.Tensor, torch.Tensor] | None = None  # (node index [N,b], weights [N,b])
        self._blend: tuple[torch.Tensor, torch.Tensor] | None = None  # sparse W [N,M] and W^T, built from it

    @property
    def node_count(self) -> int:
        return self.nodes.shape[0]

    # ------------------------------------------------------------------------------------------ binding
    @torch.no_grad()
    def bind(self, means: torch.Tensor) -> None:
        """Attach each canonical Gaussian [N,3] to its ``bind_count`` nearest nodes (Gaussian-kernel weights)."""
        count = min(self.hyper["bind_count"], self.node_count)
        sigma = self.hyper["voxel_size"]
        indices, weights = [], []
        for chunk in torch.split(means.detach(), 65536):
            distance_sq = torch.cdist(chunk, self.nodes).square()
            nearest_sq, nearest = torch.topk(distance_sq, count, dim=1, largest=False)
            kernel = torch.exp(-(nearest_sq - nearest_sq[:, :1]) / (2.0 * sigma * sigma))
            indices.append(nearest)
            weights.append(kernel / kernel.sum(dim=1, keepdim=True))
        self._set_binding(torch.cat(indices), torch.cat(weights))

    def _set_binding(self, index: torch.Tensor, weights: torch.Tensor) -> None:
        self._binding = (index, weights)
        self._blend = _blend_matrices(index, weights, self.node_count)

    def _bound(self, means: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        if self._binding is None or self._binding[0].shape[0] != means.shape[0]:
            self.bind(means)
        return self._blend

    def restore_binding(self, binding: dict | None, *, device="cpu") -> None:
        """Reinstate a binding saved by :meth:`state_for_file` (None: bind on first use)."""
        self._binding = None
        self._blend = None
        if binding is not None:
            self._set_binding(binding["index"].to(device), binding["weights"].to(device))

    def gaussian_displacement(self, means: torch.Tensor, node_displacement: torch.Tensor) -> torch.Tensor:
        """Canonical displacement [N,3] of Gaussians at canonical ``means`` [N,3], blended from the nodes'."""
        blend, blend_transposed = self._bound(means)
        return _BlendNodes.apply(node_displacement.contiguous(), blend, blend_transposed)

    def isometry(self, node_displacement: torch.Tensor) -> torch.Tensor:
        """SMAD's isometry term on the displaced graph, in units of the voxel size squared (dimensionless).

        Measured in the canonical frame, where skinning has not acted: it penalizes the stretch the
        displacement itself makes (cloth bends but hardly stretches), not the stretch linear blend skinning
        makes at bent joints, which displacements should not be asked to undo.

        Args:
            node_displacement: [M,3] this frame's canonical displacements.
        """
        displaced = (self.nodes + node_displacement).contiguous()
        return ops.isometry_loss(displaced, self.edges, self.rest_offset) / self.hyper["voxel_size"] ** 2

    def state_for_file(self) -> dict:
        """Everything to rebuild the module, including the current Gaussian binding (so a reload renders the same)."""
        binding = (None if self._binding is None
                   else {"index": self._binding[0].cpu(), "weights": self._binding[1].cpu()})
        return {"state_dict": {k: v.detach().cpu() for k, v in self.state_dict().items()}, "hyper": dict(self.hyper),
                "binding": binding}


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

