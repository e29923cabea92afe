"""SMAD's Gaussian graph (SMAD, Sec. 3.2-3.3), shared by the secondary-motion extensions.

The canonical Gaussians are voxel-downsampled into graph *nodes*, joined by k-NN edges (k = 16) whose rest
offsets are those of the canonical shape. A secondary-motion part gives every node a displacement in the
canonical (rest) frame; a Gaussian moves by the Gaussian-kernel blend of the displacements of its nearest
nodes, before linear blend skinning (so the displacement turns with the body). The graph measures the stretch
a displacement makes (SMAD's isometry term).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import torch

from warpavatar import ops
from warpavatar.extensions.base import option
from warpavatar.model.parts import AvatarPart

__all__ = ["NodeGraph", "voxel_downsample", "GraphMotionOptions", "GRAPH_PRESETS", "graph_nodes"]


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


class NodeGraph(AvatarPart):
    """SMAD's Gaussian graph: voxel-downsampled nodes, their k-NN edges and the Gaussians' binding to them.

    The base of the secondary-motion parts (:class:`~warpavatar.extensions.secondary_motion.SecondaryMotion`,
    per-frame displacements, and :class:`~warpavatar.extensions.dynamics.SecondaryDynamics`, learned
    dynamics): a part gives node displacements [M,3] in the canonical frame (:meth:`node_displacement`, or an
    explicit input of the frame), the graph blends them onto the Gaussians before skinning and measures their
    stretch.

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

    def node_displacement(self, bone_transforms: torch.Tensor) -> torch.Tensor:
        """Canonical displacement [M,3] of every node for a pose [J,4,4] (subclasses look it up)."""
        raise NotImplementedError

    def deform_canonical(self, canonical, bones, frame):
        """Displace the canonical Gaussians (before skinning, without moving where their weights are read) by
        the blend of the nodes' displacements: the frame's explicit input, else :meth:`node_displacement`."""
        displacement = frame.input(self.name)
        if displacement is None:  # learned per instant: looked up by the pose as given
            displacement = self.node_displacement(frame.bone_transforms)
        return canonical.displaced(self.gaussian_displacement(canonical.rest_means, displacement))

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


@dataclass
class GraphMotionOptions:
    """Options shared by the secondary-motion extensions on SMAD's graph (one flag sets both)."""

    secondary_from: int = option(2000, "step at which the graph is built from the canonical Gaussians and starts "
                                 "to train")
    secondary_voxel: float = option(0.03, "graph voxel edge as a fraction of the canonical box's longest side")
    lambda_isometry: float = option(0.1, "weight of SMAD's isometry loss on the posed graph (per voxel^2)")
    lambda_damping: float = option(0.01, "weight of SMAD's damping loss on node velocities (voxels per frame)")
    lambda_displacement: float = option(1e-3, "weight of the mean squared node displacement (per voxel^2)")


GRAPH_PRESETS = {"quick": {"secondary_from": 800}}
"""The graph options' values in named presets (both secondary-motion extensions declare them)."""


def graph_nodes(fit, options: GraphMotionOptions) -> tuple[torch.Tensor, float]:
    """The graph's nodes [M,3] from the current canonical Gaussians of a fit, and the voxel edge [world units]."""
    field = fit.skinning.field
    voxel = options.secondary_voxel * float((field.bbox_max - field.bbox_min).max())
    return voxel_downsample(fit.avatar.gaussians.means.detach(), voxel), voxel
