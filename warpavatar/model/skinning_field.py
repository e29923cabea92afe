"""TAGA's voxel skinning field: an MLP evaluated on a fixed coarse grid, read by trilinear interpolation.

The MLP maps a canonical grid point to bone logits; their softmax over bones is the grid of skinning weights
[D,H,W,J] (D along z, H along y, W along x, as :func:`warpavatar.ops.sample_grid` indexes). Gaussians read
their weights from the grid by trilinear interpolation, so the weights of any point are a convex combination
of softmax outputs: non-negative and summing to one. The MLP only ever sees the grid points, which keeps the
field smooth and stable while Gaussians move, split and die (TAGA Sec. 3.1).
"""

from __future__ import annotations

import math

import torch

from warpavatar import ops
from warpavatar._src.precision import mlp_matmuls
from warpavatar.geometry import Linear, fourier_features, mlp

__all__ = ["closest_on_segments", "bone_distance_prior", "bone_sample_points", "grid_shape_for_box", "box_encoding",
           "VoxelSkinningField"]


def box_encoding(points: torch.Tensor, bbox_min: torch.Tensor, bbox_max: torch.Tensor, frequencies: int
                 ) -> torch.Tensor:
    """Positional encoding [N, 3 + 6*frequencies] of points, after mapping the box to [-1, 1]^3."""
    return fourier_features((points - bbox_min) / (bbox_max - bbox_min) * 2.0 - 1.0, frequencies)


def closest_on_segments(points: torch.Tensor, heads: torch.Tensor, tails: torch.Tensor) -> torch.Tensor:
    """Closest point [N,J,3] of each bone segment head->tail ([J,3] each) to each point [N,3]."""
    axis = tails - heads  # [J,3]
    length_sq = (axis * axis).sum(-1).clamp_min(1e-12)
    rel = points[:, None, :] - heads[None]  # [N,J,3]
    t = ((rel * axis[None]).sum(-1) / length_sq).clamp(0.0, 1.0)
    return heads[None] + t[..., None] * axis[None]


def _segment_distance(points: torch.Tensor, heads: torch.Tensor, tails: torch.Tensor) -> torch.Tensor:
    """Distance [N,J] from each point to each bone segment head->tail."""
    return (points[:, None, :] - closest_on_segments(points, heads, tails)).norm(dim=-1)


def bone_distance_prior(points: torch.Tensor, heads: torch.Tensor, tails: torch.Tensor, *, temperature: float
                        ) -> torch.Tensor:
    """Rigid skinning prior [N,J]: softmax over bones of -(distance to the bone segment) / temperature.

    Uses the skeleton alone (no body template). With a small temperature it assigns each point to its nearest
    bone; it is what the field's warm-up distils and what carving poses candidate points with.
    """
    return torch.softmax(-_segment_distance(points, heads, tails) / temperature, dim=-1)


def bone_sample_points(heads: torch.Tensor, tails: torch.Tensor, parents: torch.Tensor
                       ) -> tuple[torch.Tensor, torch.Tensor]:
    """TAGA's bone-regularization samples: bone midpoints, plus a virtual point beyond each leaf joint.

    Returns:
        (points [S,3], bone index [S] of the one-hot weight expected there).
    """
    joint_count = heads.shape[0]
    points = [(heads + tails) * 0.5]
    index = [torch.arange(joint_count, device=heads.device)]
    has_child = torch.zeros(joint_count, dtype=torch.bool, device=heads.device)
    valid_parents = parents[parents >= 0].long()
    has_child[valid_parents] = True
    leaves = torch.nonzero(~has_child).squeeze(1)
    if leaves.numel():
        # the virtual joint continues the leaf bone beyond its tail by half its length
        points.append(tails[leaves] + 0.5 * (tails[leaves] - heads[leaves]))
        index.append(leaves)
    return torch.cat(points), torch.cat(index)


def grid_shape_for_box(extent: torch.Tensor, *, cells: int, min_cells: int) -> tuple[int, int, int]:
    """Grid (D, H, W) for a box of ``extent`` (x, y, z): ``cells`` along the longest axis, proportional elsewhere."""
    longest = float(extent.max())
    per_axis = [max(min_cells, min(cells, int(math.ceil(cells * float(e) / longest)))) for e in extent]
    return per_axis[2], per_axis[1], per_axis[0]


class VoxelSkinningField(torch.nn.Module):
    """Skinning weights of canonical points from an MLP distilled onto a fixed voxel grid.

    Args:
        bbox_min: [3] canonical box corner (world units); grid corners sit on the box corners.
        bbox_max: [3] opposite corner.
        joint_count: number of bones J (weights per point).
        cells: grid cells along the box's longest axis (TAGA uses 64x64x16).
        min_cells: fewest cells along any axis.
        hidden: MLP width.
        layers: MLP hidden layers.
        frequencies: positional-encoding octaves of the grid coordinates.
    """

    def __init__(self, bbox_min: torch.Tensor, bbox_max: torch.Tensor, joint_count: int, *, cells: int = 64,
                 min_cells: int = 16, hidden: int = 128, layers: int = 4, frequencies: int = 6):
        super().__init__()
        self.register_buffer("bbox_min", bbox_min.float().clone())
        self.register_buffer("bbox_max", bbox_max.float().clone())
        self.joint_count = joint_count
        self.frequencies = frequencies
        self.hyper = dict(cells=cells, min_cells=min_cells, hidden=hidden, layers=layers, frequencies=frequencies)
        self.grid_shape = grid_shape_for_box(bbox_max - bbox_min, cells=cells, min_cells=min_cells)
        depth, height, width = self.grid_shape
        axes = [torch.linspace(0.0, 1.0, count) for count in (depth, height, width)]
        gz, gy, gx = torch.meshgrid(*axes, indexing="ij")
        unit = torch.stack([gx, gy, gz], dim=-1)  # [D,H,W,3] in 0..1, x first
        self.register_buffer("grid_points", (bbox_min.cpu() + unit * (bbox_max - bbox_min).cpu()).to(bbox_min))
        self.mlp = mlp(3 + 3 * 2 * frequencies, hidden, layers, joint_count,
                       activation=lambda: torch.nn.Softplus(beta=10.0))
        # The MLP only ever sees the grid points: encode them once (derived, so not saved in state dicts).
        self.register_buffer("grid_encoding", self._encode(self.grid_points.reshape(-1, 3)), persistent=False)

    def _encode(self, points: torch.Tensor) -> torch.Tensor:
        return box_encoding(points, self.bbox_min, self.bbox_max, self.frequencies)

    def cell_encoding(self, cells: torch.Tensor) -> torch.Tensor:
        """The MLP's input [A, 3 + 6*frequencies] at some grid points (``cells``: [A] flat indices), to keep for
        as long as the same points are evaluated (:meth:`cell_weights`' ``encoding``)."""
        return self.grid_encoding.index_select(0, cells)

    def _logits(self, cells: torch.Tensor | None = None, encoding: torch.Tensor | None = None) -> torch.Tensor:
        """The MLP's bone logits at every grid point [D*H*W, J], or at ``cells`` (flat indices [A]) only, whose
        inputs may be given (``encoding``: :meth:`cell_encoding` of ``cells``)."""
        if encoding is None:
            encoding = self.grid_encoding if cells is None else self.cell_encoding(cells)
        with mlp_matmuls(encoding.device):
            return self.mlp(encoding)

    def grid_weights(self) -> torch.Tensor:
        """The voxel grid of skinning weights [D,H,W,J] (softmax of the MLP at the grid points)."""
        return torch.softmax(self._logits(), dim=-1).reshape(*self.grid_shape, self.joint_count)

    @property
    def cell_count(self) -> int:
        """Number of grid points D*H*W (the rows of a flattened grid)."""
        depth, height, width = self.grid_shape
        return depth * height * width

    def cell_weights(self, cells: torch.Tensor, *, encoding: torch.Tensor | None = None) -> torch.Tensor:
        """Skinning weights [A,J] of some grid points (``cells``: [A] flat indices into the [D*H*W] grid): the
        rows of :meth:`grid_weights` for those points, computed by the MLP at those points only (from
        ``encoding``, their :meth:`cell_encoding`, when given)."""
        return torch.softmax(self._logits(cells, encoding), dim=-1)

    @torch.no_grad()
    def cells_read_by(self, points: torch.Tensor, *, dilation: int = 1) -> torch.Tensor:
        """Flat indices [A] (sorted) of the grid points that trilinear interpolation at ``points`` [N,3] reads
        (the 8 corners of each point's cell, with border clamping as :meth:`weights`), grown by ``dilation``
        cells along each axis (points that move by less than that still read only these). One host read."""
        if points.shape[0] == 0:
            return torch.zeros(0, dtype=torch.long, device=points.device)
        sizes = torch.tensor(self.grid_shape[::-1], device=points.device)  # (W, H, D): x, y, z
        unit = (points.detach().float() - self.bbox_min) / (self.bbox_max - self.bbox_min)
        lower = torch.floor(unit * (sizes - 1).float()).long()
        lower = torch.minimum(torch.clamp(lower, min=0), torch.clamp(sizes - 2, min=0))
        marked = torch.zeros(self.grid_shape, device=points.device)
        marked[lower[:, 2], lower[:, 1], lower[:, 0]] = 1.0
        # A grid point c is read by a point whose lower corner lies in [c - 1 - dilation, c + dilation] per axis:
        # a max filter of width 2 + 2 * dilation over the marked lower corners, padded 1 + dilation before.
        padded = torch.nn.functional.pad(marked[None, None], (1 + dilation, dilation) * 3)
        read = torch.nn.functional.max_pool3d(padded, kernel_size=2 + 2 * dilation, stride=1)[0, 0]
        return torch.nonzero(read.reshape(-1) > 0).squeeze(1)

    def weights(self, points: torch.Tensor, grid: torch.Tensor | None = None) -> torch.Tensor:
        """Skinning weights [N,J] of canonical points [N,3] by trilinear interpolation of the grid.

        Points outside the box take the weights of the nearest box face (border clamping).
        """
        grid = self.grid_weights() if grid is None else grid
        return ops.sample_grid(grid, points, self.bbox_min, self.bbox_max)

    def distillation_loss(self, prior: torch.Tensor, cells: torch.Tensor | None = None) -> torch.Tensor:
        """Cross-entropy of the grid's weights against a prior [D*H*W, J] (the warm-up objective), over every grid
        point or over ``cells`` (flat indices [A]) only."""
        target = prior if cells is None else prior.index_select(0, cells)
        return -(target * torch.log_softmax(self._logits(cells), dim=-1)).sum(-1).mean()

    @torch.no_grad()
    def add_joints(self, parents: torch.Tensor) -> None:
        """Add one output per grown joint (ToMiE Sec. 4.4), each starting as a copy of its parent's.

        The parent's logit and its copies are all lowered by log(1 + number of children), so the parent's
        weight is split evenly between itself and its children: the summed weight of the group, and so any pose in
        which the children move with the parent, is unchanged. Training then decides where the children take over.

        Args:
            parents: [E] index of each new joint's parent among the current outputs.
        """
        parents = torch.as_tensor(parents).long().reshape(-1).cpu()
        if parents.numel() == 0:
            return
        if int(parents.min()) < 0 or int(parents.max()) >= self.joint_count:
            raise ValueError(f"parents must index the field's {self.joint_count} joints, got {parents.tolist()}")
        old = self.mlp[-1]
        weight, bias = old.weight.detach().clone(), old.bias.detach().clone()
        shares = torch.ones(self.joint_count) + torch.bincount(parents, minlength=self.joint_count).float()
        bias = bias - torch.log(shares).to(bias)
        new = Linear(old.in_features, self.joint_count + parents.numel()).to(weight)
        new.weight.copy_(torch.cat([weight, weight[parents.to(weight.device)]]))
        new.bias.copy_(torch.cat([bias, bias[parents.to(bias.device)]]))
        self.mlp[-1] = new
        self.joint_count += int(parents.numel())

    def bone_loss(self, sample_points: torch.Tensor, sample_bones: torch.Tensor, grid: torch.Tensor | None = None,
                  *, groups: torch.Tensor | None = None) -> torch.Tensor:
        """TAGA's bone regularization: squared distance of the weights at bone samples from one-hot vectors.

        Args:
            sample_points: [S,3] canonical sample points (:func:`bone_sample_points`).
            sample_bones: [S] bone whose one-hot weight is expected at each sample.
            grid: precomputed grid of weights.
            groups: [J',J] 0/1 matrix, for grown joints (ToMiE): row j' marks the skeleton joint output j'
                counts towards (a grown joint's parent, itself for the others). The weights of a group are
                summed before comparing, so how a parent shares its region with its children is left free.
        """
        weights = self.weights(sample_points, grid)
        if groups is not None:
            weights = weights @ groups.to(weights)
        # (one_hot would check the indices' range on the host)
        target = torch.zeros_like(weights).scatter_(1, sample_bones[:, None], 1.0)
        return ((weights - target) ** 2).sum(-1).mean()
