"""A mass-spring cloth on a garment's node graph, stepped by explicit (semi-implicit) Euler substeps.

Nodes and graph. The nodes are points of the garment in its rest shape (e.g. voxel-downsampled garment
Gaussians). :func:`cloth_graph` joins them by *stretch* edges, the k-NN pairs of the rest shape (symmetric:
a pair is one edge whatever direction found it), and *bend* edges, pairs of the second ring (neighbours of
neighbours that are not neighbours), at most ``bend_per_node`` nearest ones started from each node. Some
nodes are *attached*: they follow targets the caller gives per frame (the skinned positions of the points of
the garment held by the body: waistband, shoulders); the rest are free particles.

Forces on a free node ``i`` (mass ``m_i``), per substep of ``h`` seconds:

* gravity ``m_i g``, with ``g = -9.81 up`` by default (``up`` of skeleton.json, ``+z`` in the supplied data);
* length springs on every edge ``e = (i, j)`` (stretch and bend alike), ``-k_e (|d| - L_e) d/|d|`` with
  ``d = x_i - x_j``: the exact length spring, given to :func:`warpavatar.ops.spring_step` as the rest offset
  ``L'_e d/|d|`` recomputed at every substep by :func:`warpavatar.ops.cloth_edge_terms` (with the damping),
  where ``L'_e = min(L_e, 2 |d|)`` (a spring squeezed below half its rest length pushes no harder than
  ``k_e |d|``: the transverse stiffness ``k_e (1 - L'_e/|d|)`` of the spring stays within ``[-k_e, k_e]``
  however short the edge gets);
* damping of the relative velocity on every edge, ``-c_e (v_i - v_j)``;
* linear air drag ``-a_i v_i`` (the air at rest);
* an optional external acceleration (the hook of a learned force), bounded smoothly:
  ``a / sqrt(1 + |a|^2 / a_max^2)``.

Stability for any parameter value. Every learned quantity is a squashed logit, so it stays in a range fixed
at construction for the longest substep ``h <= max_substep``. With the masses' lower bound
``m-_i = m0_i / mass_range``, a node's stretch and bend degrees ``n^s_i``, ``n^b_i`` and, for a stretch edge,
``mu_e = min(m-_i / n^s_i, m-_j / n^s_j)`` (bend edges likewise with ``n^b``):

* stiffness ``k_e = sigmoid(z) * 0.5 * share * mu_e / max_substep^2`` with ``share`` 0.8 for stretch edges and 0.2
  for bend edges, so ``sum_{e at i} k_e <= 0.5 m_i / h^2``: the Gershgorin bound ``sum of stiffness at a node
  <= c m / h^2`` with ``c = 0.5``. Every 3x3 block of the springs' Jacobian has norm at most ``k_e``, so the
  largest eigenvalue of ``M^-1 K`` is at most ``2 sum_{e at i} k_e / m_i <= 1 / h^2``;
* edge damping ``c_e = sigmoid(z) * 0.25 * mu'_e / max_substep`` (``mu'`` with the total degree) and drag
  ``a_i = sigmoid(z) * 0.25 m-_i / max_substep`` (plus at most as much again while settling), so the damping
  rate is at most ``h (2 sum c_e + a_i) / m_i <= 1`` (damping ``<= m / h``).

For the damped oscillator ``m x'' = -k x - c x'`` semi-implicit Euler is stable while ``h c / m <= 1`` and
``h^2 k / m <= 4 - 2 h c / m`` (the Jury conditions of its 2x2 step matrix); the bounds keep
``h^2 omega^2 <= 1`` and ``h c / m <= 1``, inside that region with a factor 2 to spare (springs pushed into
compression may still buckle, as cloth does, at a rate bounded by the same numbers). Rest lengths stay
within ``[0.5, 1.5]`` times their rest-shape values, the mass scale within ``[1 / mass_range, mass_range]``.

A learnable rest shape (``rest_offset_bound > 0``). The rest positions are the initial ones plus a bounded
offset per free node, ``P_i = X_i + b z_i / sqrt(1 + |z_i|^2)`` (``|P_i - X_i| < b``; attached nodes keep
``X_i``), and every edge's rest-shape length is ``|P_i - P_j|`` (then scaled by its ``[0.5, 1.5]`` factor), so
a wider hem has longer hem springs. The stability bounds above depend on the masses alone, so they hold for
any rest shape. Two penalties keep the shape plausible: :meth:`ClothModel.rest_shape_roughness` (the offsets'
graph Laplacian) and :meth:`ClothModel.rest_shape_collapse` (stretch edges shorter than half their initial
length).

The price of an explicit step: a stretch spring can be at most ``0.4 m- / (n^s h^2)`` stiff, so a hanging
chain of ``N`` nodes of mass ``m`` stretches by at least about ``N^2 g n^s h^2 m / (0.8 m-)`` in all (its
springs carry ``N^2 m g / 2`` of weight between them): stiff cloth needs a small ``max_substep`` (1/240 s suits
soft, stretchy garments; 1/1000 s and below stiffer ones).

Strain limiting (``strain_limit > 1``). Real cloth barely stretches, which an explicit step cannot model with
springs alone: the stiffness bound above lets a hanging skirt stretch by tens of per cent under its own weight.
After every substep (after the collision push) ``strain_iterations`` Jacobi passes of Provot's strain limiting
(1995, "Deformation constraints in a mass-spring model to describe rigid cloth behavior") pull every stretch edge
longer than ``strain_limit`` times its rest length back towards it: each free node moves by the mean, over its
violated stretch edges, of its share of the excess (half, or all of it when the other end is attached), and its
velocity by that move over ``h`` (an edge counts in the mean from 0 at its limit to fully at 1 % past it, so
the move does not jump when an edge crosses its limit). A pass moves a node only toward neighbours it is too far
from, by at most its share of the excess, so it brings no instability of its own; a cloth whose edges are all
within the limit is not touched.

Attachment and collision. Attached nodes move on the straight line from where they are to their new
targets over the frame's substeps, with that line's velocity. After every substep the free nodes are pushed
out of the body's capsules (:func:`warpavatar.ops.push_out_of_capsules`) and their velocity is corrected by
the same move over ``h``, so position and velocity stay consistent (a node that hits the body keeps no
velocity into it). Capsules may move during the frame (linear between the previous frame's and this one's).

With gradients, everything is torch autograd through ``cloth_edge_terms``, ``spring_step`` and the collision
op (truncating the window is the caller's business), with no host synchronization per substep: the number of
substeps is computed from the Python number ``frame_interval``. Without gradients (settling, rollouts,
every consumer of a fitted garment) a float32 frame runs fused instead (:mod:`warpavatar.kernels.cloth_frame`):
one kernel launch per substep, one thread per node over the receiver-sorted edges, the same maths within
float32 rounding; its coefficients are cached per model until a parameter or buffer changes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from warpavatar import ops
from warpavatar._src.cloth_frame import ClothFrame, csr_rows
from warpavatar.kernels.cloth_frame import STRAIN_RAMP

__all__ = ["ClothGraph", "cloth_graph", "ClothState", "Capsules", "ClothModel"]

REST_LENGTH_RANGE = (0.5, 1.5)
"""Rest lengths stay within these multiples of their rest-shape values."""

STIFFNESS_FRACTION = 0.5
"""``c`` of the Gershgorin bound ``sum of stiffness at a node <= c m / h^2``."""
STRETCH_SHARE = 0.8
"""Part of a node's stiffness budget that its stretch edges may use (the bend edges use the rest)."""
DAMPING_FRACTION = 0.25
DRAG_FRACTION = 0.25
REST_COLLAPSE_RATIO = 0.5
"""A stretch edge of the learned rest shape shorter than this fraction of its initial length is penalized by
:meth:`ClothModel.rest_shape_collapse`."""


@dataclass
class ClothGraph:
    """Edges of a cloth: undirected node pairs, int64 ``[S, 2]`` (stretch) and ``[B, 2]`` (bend), ``i < j``."""

    stretch: torch.Tensor
    bend: torch.Tensor


@dataclass
class ClothState:
    """Positions and velocities of every node [world units, world units / s], ``[M, 3]`` each."""

    positions: torch.Tensor
    velocities: torch.Tensor


@dataclass
class Capsules:
    """Collision capsules: segment endpoints ``[C, 3]`` and radii ``[C]`` [world units] (see
    :func:`warpavatar.ops.push_out_of_capsules`)."""

    segment_start: torch.Tensor
    segment_end: torch.Tensor
    radius: torch.Tensor


def _pair_keys(pairs: torch.Tensor, node_count: int) -> torch.Tensor:
    return pairs[:, 0] * node_count + pairs[:, 1]


def _unique_pairs(first: torch.Tensor, second: torch.Tensor, node_count: int) -> torch.Tensor:
    """Sorted undirected pairs ``[P, 2]`` (``i < j``) of the valid, distinct pairs among ``(first, second)``."""
    valid = (first >= 0) & (second >= 0) & (first != second)
    low, high = torch.minimum(first, second)[valid], torch.maximum(first, second)[valid]
    keys = torch.unique(low * node_count + high)
    return torch.stack([keys // node_count, keys % node_count], dim=1)


def cloth_graph(rest_positions: torch.Tensor, *, neighbours: int = 8, bend_per_node: int = 8) -> ClothGraph:
    """Stretch and bend edges of a cloth from its rest shape.

    Args:
        rest_positions: node positions in the rest shape [world units], float ``[M, 3]``.
        neighbours: k of the k-NN graph whose symmetric pairs are the stretch edges (``1..64``).
        bend_per_node: second-ring pairs started from each node, nearest first (0: no bend edges).

    Returns:
        The :class:`ClothGraph`, on the device of ``rest_positions``.

    Raises:
        ValueError: ``neighbours`` or ``bend_per_node`` out of range (and what :func:`ops.knn_graph` raises).
    """
    if bend_per_node < 0:
        raise ValueError(f"bend_per_node must be >= 0, got {bend_per_node}")
    node_count = rest_positions.shape[0]
    points = rest_positions.detach().float()
    index, _ = ops.knn_graph(points, neighbours)  # [M, k], -1 padded
    rows = torch.arange(node_count, device=points.device)[:, None].expand_as(index)
    stretch = _unique_pairs(rows.reshape(-1), index.reshape(-1), node_count)
    if bend_per_node == 0 or node_count == 0:
        return ClothGraph(stretch, stretch.new_zeros((0, 2)))
    # second ring: neighbours (k-NN rows) of neighbours, minus the node itself and its stretch partners
    safe = index.clamp_min(0)
    ring = index[safe].reshape(node_count, -1)  # [M, k*k]
    ring = torch.where((index < 0)[:, :, None].expand(-1, -1, index.shape[1]).reshape(node_count, -1), -1, ring)
    source = rows[:, :1].expand_as(ring)
    low, high = torch.minimum(source, ring), torch.maximum(source, ring)
    is_stretch = torch.isin(low * node_count + high, _pair_keys(stretch, node_count))
    usable = (ring >= 0) & (ring != source) & ~is_stretch
    # one candidate per distinct partner (sort by partner, drop repeats), then the nearest ones
    ring, order = torch.where(usable, ring, node_count).sort(dim=1)
    repeat = torch.zeros_like(usable)
    repeat[:, 1:] = ring[:, 1:] == ring[:, :-1]
    usable = (ring < node_count) & ~repeat
    distance = (points[:, None] - points[ring.clamp_max(node_count - 1)]).norm(dim=-1)
    distance = torch.where(usable, distance, torch.inf)
    nearest = distance.argsort(dim=1)[:, :bend_per_node]
    chosen = torch.gather(ring, 1, nearest)
    chosen = torch.where(torch.gather(usable, 1, nearest), chosen, -1)
    bend = _unique_pairs(source[:, : chosen.shape[1]].reshape(-1), chosen.reshape(-1), node_count)
    return ClothGraph(stretch, bend)


def _logit(fraction: float) -> float:
    return math.log(fraction / (1.0 - fraction))


class ClothModel(torch.nn.Module):
    """A cloth's learnable physics: rest lengths, stiffness, damping, drag and mass, bounded for stability.

    Args:
        rest_positions: node positions in the rest shape [world units], float ``[M, 3]``.
        graph: its edges (:func:`cloth_graph`).
        attached: ids of the attached nodes, integer ``[A]`` (their positions come from the caller's targets).
        node_mass: mass of each node [kg], a number or float ``[M]`` (positive).
        max_substep: longest substep [s]; a frame of ``dt`` seconds takes ``ceil(dt / max_substep)`` substeps.
            The parameter ranges scale with it (see the module docstring).
        gravity: gravitational acceleration [world units / s^2], ``[3]``; default ``-9.81 * up``.
        up: the world's up direction (skeleton.json's ``up``), used when ``gravity`` is None.
        mass_range: the mass scale stays within ``[1 / mass_range, mass_range]`` (> 1).
        max_external_acceleration: bound of the external acceleration hook [world units / s^2].
        stretch_stiffness, bend_stiffness, damping, drag: initial values as fractions ``(0, 1)`` of their bounds.
        rest_offset_bound: how far the learnable rest shape may move a free node from ``rest_positions``
            [world units], ``>= 0``; 0 (default): the rest shape is fixed and the model has no
            ``rest_offset_logit`` parameter (see the module docstring).
        strain_limit: the longest a stretch edge may get after a substep, as a multiple of its rest length
            (``> 1``); 0 (default): no strain limiting (see the module docstring).
        strain_iterations: Jacobi passes of strain limiting per substep (``>= 1`` with a ``strain_limit``).

    Raises:
        ValueError: bad shapes, attached ids outside ``[0, M)`` or repeated, a non-positive mass, options out
            of range.
    """

    def __init__(
        self,
        rest_positions: torch.Tensor,
        graph: ClothGraph,
        attached: torch.Tensor,
        *,
        node_mass: float | torch.Tensor = 1e-3,
        max_substep: float = 1.0 / 240.0,
        gravity: torch.Tensor | None = None,
        up: tuple[float, float, float] = (0.0, 0.0, 1.0),
        mass_range: float = 2.0,
        max_external_acceleration: float = 30.0,
        stretch_stiffness: float = 0.9,
        bend_stiffness: float = 0.1,
        damping: float = 0.1,
        drag: float = 0.02,
        rest_offset_bound: float = 0.0,
        strain_limit: float = 0.0,
        strain_iterations: int = 8,
    ):
        super().__init__()
        if not (strain_limit == 0.0 or strain_limit > 1.0):
            raise ValueError(f"strain_limit must be 0 (off) or > 1, got {strain_limit}")
        if strain_limit and not (isinstance(strain_iterations, int) and strain_iterations >= 1):
            raise ValueError(f"strain_iterations must be an integer >= 1, got {strain_iterations}")
        self.strain_limit = float(strain_limit)
        self.strain_iterations = int(strain_iterations) if strain_limit else 0
        if not rest_offset_bound >= 0.0:
            raise ValueError(f"rest_offset_bound must be >= 0, got {rest_offset_bound}")
        if not max_substep > 0.0:
            raise ValueError(f"max_substep must be > 0, got {max_substep}")
        if not mass_range > 1.0:
            raise ValueError(f"mass_range must be > 1, got {mass_range}")
        for name, fraction in (("stretch_stiffness", stretch_stiffness), ("bend_stiffness", bend_stiffness),
                               ("damping", damping), ("drag", drag)):
            if not 0.0 < fraction < 1.0:
                raise ValueError(f"{name} is a fraction of its bound and must be in (0, 1), got {fraction}")
        if rest_positions.dim() != 2 or rest_positions.shape[1] != 3:
            raise ValueError(f"rest_positions must have shape [M, 3], got {list(rest_positions.shape)}")
        device = rest_positions.device
        rest = rest_positions.detach().float()
        node_count = rest.shape[0]
        attached = torch.as_tensor(attached, device=device).reshape(-1)
        if attached.numel() and (int(attached.min()) < 0 or int(attached.max()) >= node_count
                                 or attached.unique().numel() != attached.numel()):
            raise ValueError(f"attached must hold distinct node ids in [0, {node_count})")
        pairs = torch.cat([graph.stretch, graph.bend]).to(device=device, dtype=torch.int64)
        self.stretch_count = graph.stretch.shape[0]
        self.max_substep = float(max_substep)
        self.mass_range = float(mass_range)
        self.max_external_acceleration = float(max_external_acceleration)
        mass = torch.as_tensor(node_mass, dtype=torch.float32, device=device).expand(node_count).clone()
        if node_count and not bool((mass > 0).all()):
            raise ValueError("node_mass must be positive")

        # directed edges (both directions of every pair), sorted by receiver for spring_step
        directed = torch.cat([pairs, pairs.flip(1)])
        pair_of_directed = torch.arange(pairs.shape[0], device=device).repeat(2)
        order = torch.argsort(directed[:, 0] * max(node_count, 1) + directed[:, 1])
        self.register_buffer("pairs", pairs)
        self.register_buffer("edges", directed[order].to(torch.int32).contiguous())
        # node i receives edges row_start[i]:row_start[i+1] (the fused frame's CSR; not saved: made from the edges)
        self.register_buffer("edge_row_start", csr_rows(directed[order][:, 0], node_count), persistent=False)
        self.register_buffer("pair_of_edge", pair_of_directed[order].contiguous())
        self.register_buffer("attached", attached.to(torch.int64))
        self.register_buffer("base_mass", mass)
        self.register_buffer("rest_length", (rest[pairs[:, 0]] - rest[pairs[:, 1]]).norm(dim=1))
        self.register_buffer("initial_rest_positions", rest.clone())
        self.rest_offset_bound = float(rest_offset_bound)
        if gravity is None:
            up_vector = torch.tensor(up, dtype=torch.float32)
            gravity = -9.81 * up_vector / up_vector.norm()
        self.register_buffer("gravity", torch.as_tensor(gravity, dtype=torch.float32, device=device).reshape(3))

        # bounds (see the module docstring): the lightest masses shared among a node's edges of each kind
        light = mass / self.mass_range
        is_stretch = torch.arange(pairs.shape[0], device=device) < self.stretch_count

        def share_of(selected: torch.Tensor) -> torch.Tensor:
            ends = pairs[selected].reshape(-1)
            degree = torch.zeros(node_count, device=device).index_add_(0, ends, torch.ones(ends.numel(), device=device))
            share = light / degree.clamp_min(1.0)
            return torch.minimum(share[pairs[:, 0]], share[pairs[:, 1]])

        kind_share = torch.where(is_stretch, STRETCH_SHARE, 1.0 - STRETCH_SHARE)
        stiffness_mu = torch.where(is_stretch, share_of(is_stretch), share_of(~is_stretch))
        self.register_buffer("stiffness_bound", STIFFNESS_FRACTION * kind_share * stiffness_mu / self.max_substep**2)
        all_pairs = torch.ones_like(is_stretch)
        self.register_buffer("damping_bound", DAMPING_FRACTION * share_of(all_pairs) / self.max_substep)
        self.register_buffer("drag_bound", DRAG_FRACTION * light / self.max_substep)

        pair_count = pairs.shape[0]
        stiffness_init = torch.cat([torch.full((self.stretch_count,), _logit(stretch_stiffness)),
                                    torch.full((pair_count - self.stretch_count,), _logit(bend_stiffness))])
        self.rest_length_logit = torch.nn.Parameter(torch.zeros(pair_count, device=device))
        self.stiffness_logit = torch.nn.Parameter(stiffness_init.to(device))
        self.damping_logit = torch.nn.Parameter(torch.tensor(_logit(damping), device=device))
        self.drag_logit = torch.nn.Parameter(torch.tensor(_logit(drag), device=device))
        self.mass_logit = torch.nn.Parameter(torch.tensor(0.0, device=device))
        self.rest_offset_logit = (torch.nn.Parameter(torch.zeros(node_count, 3, device=device))
                                  if self.rest_offset_bound > 0.0 else None)

    # ------------------------------------------------------------------------------------ bounded values
    @property
    def node_count(self) -> int:
        return self.base_mass.shape[0]

    def rest_positions(self) -> torch.Tensor:
        """Node positions of the rest shape [world units], ``[M, 3]``: the initial ones plus the learned bounded
        offsets (attached nodes keep theirs); differentiable with respect to ``rest_offset_logit``."""
        if self.rest_offset_logit is None:
            return self.initial_rest_positions
        z = self.rest_offset_logit
        offset = self.rest_offset_bound * z * torch.rsqrt(1.0 + (z * z).sum(dim=1, keepdim=True))
        return self.initial_rest_positions + offset.index_fill(0, self.attached, 0.0)

    def rest_shape_lengths(self) -> torch.Tensor:
        """Length of every pair (stretch then bend) in the rest shape [world units], ``[P]``."""
        if self.rest_offset_logit is None:
            return self.rest_length
        rest = self.rest_positions()
        return (rest.index_select(0, self.pairs[:, 0]) - rest.index_select(0, self.pairs[:, 1])).norm(dim=1)

    def rest_lengths(self) -> torch.Tensor:
        """Rest length of every pair (stretch then bend) [world units], ``[P]``: its rest-shape length times its
        learned factor in ``[0.5, 1.5]``."""
        low, high = REST_LENGTH_RANGE
        return self.rest_shape_lengths() * (low + (high - low) * torch.sigmoid(self.rest_length_logit))

    def rest_shape_roughness(self) -> torch.Tensor:
        """How unevenly the rest shape moved: the mean over nodes of ``|o_i - mean_j o_j|^2``, ``o`` the rest
        offsets and ``j`` the node's stretch neighbours, over the squared mean initial stretch length
        (dimensionless; 0 for a rest shape that did not move or moved rigidly by a translation)."""
        if self.rest_offset_logit is None:
            return self.initial_rest_positions.new_zeros(())
        offset = self.rest_positions() - self.initial_rest_positions
        stretch = self.pairs[: self.stretch_count]
        if stretch.shape[0] == 0:
            return offset.new_zeros(())
        ends, others = torch.cat([stretch[:, 0], stretch[:, 1]]), torch.cat([stretch[:, 1], stretch[:, 0]])
        total = torch.zeros_like(offset).index_add_(0, ends, offset.index_select(0, others))
        degree = torch.zeros(offset.shape[0], device=offset.device, dtype=offset.dtype).index_add_(
            0, ends, torch.ones_like(ends, dtype=offset.dtype))
        # (the mean over the nodes that have neighbours as a weighted sum: no boolean indexing, which would read
        # the device, so a captured training step can compute it)
        has_neighbours = (degree > 0).to(offset.dtype)
        laplacian = offset - total / degree.clamp_min(1.0)[:, None]
        scale = self.rest_length[: self.stretch_count].mean().clamp_min(1e-12)
        roughness = ((laplacian * laplacian).sum(dim=1) * has_neighbours).sum() / has_neighbours.sum().clamp_min(1.0)
        return roughness / scale**2

    def rest_shape_collapse(self) -> torch.Tensor:
        """How far stretch edges of the rest shape shrank below :data:`REST_COLLAPSE_RATIO` of their initial
        length: the mean over stretch edges of ``max(0, 0.5 - l / L)^2`` (dimensionless)."""
        if self.rest_offset_logit is None or self.stretch_count == 0:
            return self.initial_rest_positions.new_zeros(())
        ratio = (self.rest_shape_lengths()[: self.stretch_count]
                 / self.rest_length[: self.stretch_count].clamp_min(1e-12))
        return torch.relu(REST_COLLAPSE_RATIO - ratio).square().mean()

    def stiffness(self) -> torch.Tensor:
        """Spring stiffness of every pair [N / world unit], ``[P]``."""
        return self.stiffness_bound * torch.sigmoid(self.stiffness_logit)

    def edge_damping(self) -> torch.Tensor:
        """Relative-velocity damping of every pair [N s / world unit], ``[P]``."""
        return self.damping_bound * torch.sigmoid(self.damping_logit)

    def drag(self) -> torch.Tensor:
        """Air drag of every node [N s / world unit], ``[M]``."""
        return self.drag_bound * torch.sigmoid(self.drag_logit)

    def masses(self) -> torch.Tensor:
        """Node masses [kg], ``[M]``."""
        return self.base_mass * torch.exp(math.log(self.mass_range) * torch.tanh(self.mass_logit))

    def substeps(self, frame_interval: float) -> int:
        """Substeps of a frame of ``frame_interval`` seconds."""
        return max(1, math.ceil(float(frame_interval) / self.max_substep - 1e-9))

    def bounded_acceleration(self, acceleration: torch.Tensor) -> torch.Tensor:
        """The external acceleration hook's smooth bound: ``a / sqrt(1 + |a|^2 / a_max^2)``."""
        ratio = (acceleration * acceleration).sum(-1, keepdim=True) / self.max_external_acceleration**2
        return acceleration * torch.rsqrt(1.0 + ratio)

    # ---------------------------------------------------------------------------------------- stepping
    def rest_state(self, rest_positions: torch.Tensor) -> ClothState:
        """A state at ``rest_positions`` [M,3], at rest."""
        return ClothState(rest_positions, torch.zeros_like(rest_positions))

    def step(
        self,
        state: ClothState,
        attachment_targets: torch.Tensor,
        frame_interval: float,
        *,
        capsules: Capsules | None = None,
        previous_capsules: Capsules | None = None,
        external_acceleration: torch.Tensor | None = None,
        extra_drag: float = 0.0,
        fused: bool | None = None,
    ) -> ClothState:
        """Advance the cloth by one frame.

        Without gradients (``torch.is_grad_enabled()`` False, or neither the parameters nor any input requires
        one) a float32 frame runs fused: one Warp kernel launch per substep (:mod:`warpavatar.kernels.cloth_frame`),
        same results within float32 rounding (sums in another order). With gradients it runs op by op through
        torch autograd.

        Args:
            state: the state at the end of the previous frame (attached nodes at their previous targets).
            attachment_targets: where the attached nodes are at the end of this frame [world units], ``[A, 3]``.
            frame_interval: the frame's duration [s], a Python number > 0.
            capsules: the body's capsules at the end of the frame (None: no collision).
            previous_capsules: the capsules at the start of the frame (None: ``capsules`` all frame long).
            external_acceleration: a (learned) acceleration of each node [world units / s^2], ``[M, 3]``,
                bounded by ``max_external_acceleration``.
            extra_drag: added drag as a fraction of the drag's bound, ``[0, 1]`` (settling uses it; the
                total stays within the stability bound).
            fused: True: the fused frame (no gradients flow through it); False: op by op; None (default):
                fused exactly when no gradient is needed.

        Returns:
            The state at the end of the frame.
        """
        if not frame_interval > 0.0:
            raise ValueError(f"frame_interval must be > 0, got {frame_interval}")
        if not 0.0 <= extra_drag <= 1.0:
            raise ValueError(f"extra_drag must be in [0, 1], got {extra_drag}")
        if attachment_targets.shape != (self.attached.shape[0], 3):
            raise ValueError(f"attachment_targets must have shape [{self.attached.shape[0]}, 3], "
                             f"got {list(attachment_targets.shape)}")
        substeps = self.substeps(frame_interval)
        if fused is None:  # (the fused kernel is float32: float64 rollouts, such as references, go op by op)
            fused = state.positions.dtype == self.base_mass.dtype == torch.float32 and not self._needs_gradient(
                state, attachment_targets, capsules, previous_capsules, external_acceleration)
        if fused:
            return self._fused_frame(state, attachment_targets, frame_interval, substeps, capsules, previous_capsules,
                                     external_acceleration, extra_drag)
        h = float(frame_interval) / substeps
        x, v = state.positions, state.velocities
        mass, stiffness, rest_length, edge_damping, drag = self._coefficients(extra_drag)
        constant_force = self._constant_force(mass, external_acceleration)
        start = x.index_select(0, self.attached)
        attached_velocity = (attachment_targets - start) / float(frame_interval)
        limits = self.strain_limits() if self.strain_iterations else None
        for substep in range(1, substeps + 1):
            fraction = substep / substeps
            rest_offset, damping_force = ops.cloth_edge_terms(x, v, self.edges, rest_length, edge_damping)
            x, v = ops.spring_step(x, v, self.edges, rest_offset, stiffness, drag, mass, constant_force + damping_force,
                                   h)
            # (the last substep lands on the targets themselves, bit for bit)
            target = attachment_targets if substep == substeps else start + fraction * (attachment_targets - start)
            x = x.index_copy(0, self.attached, target)
            v = v.index_copy(0, self.attached, attached_velocity)
            if capsules is not None:
                shape = capsules if previous_capsules is None else _interpolate(previous_capsules, capsules, fraction)
                pushed = ops.push_out_of_capsules(x, shape.segment_start, shape.segment_end, shape.radius)
                pushed = pushed.index_copy(0, self.attached, target)
                v = v + (pushed - x) / h
                x = pushed
            if self.strain_iterations:
                x, v = self._limit_strain(x, v, limits, h)
        return ClothState(x, v)

    frame_cuda_graph = False
    """On CUDA, replay each fused frame's launches as one CUDA graph captured on first use (per frame length,
    capsule count and parameter values); a failed capture warns and goes on without."""

    def __getstate__(self):
        # (the fused frame's cache holds Warp views of this module's tensors: a copy makes its own)
        state = super().__getstate__().copy()
        state.pop("_frame_key", None)
        state.pop("_frames", None)
        return state

    def _needs_gradient(self, state, attachment_targets, capsules, previous_capsules, external_acceleration) -> bool:
        if not torch.is_grad_enabled():
            return False
        tensors = [state.positions, state.velocities, attachment_targets, external_acceleration,
                   *(_capsule_tensors(capsules) or ()), *(_capsule_tensors(previous_capsules) or ())]
        return any(t is not None and t.requires_grad for t in [*tensors, *self._parameters.values()])

    def strain_limits(self) -> torch.Tensor:
        """The longest every directed edge may get after a substep [world units], ``[E]``: ``strain_limit`` times
        the rest length of stretch edges, 0 (no limit) for bend edges and without strain limiting."""
        limit = self.rest_lengths() * self.strain_limit
        limit = limit.masked_fill(torch.arange(limit.shape[0], device=limit.device) >= self.stretch_count, 0.0)
        return limit.index_select(0, self.pair_of_edge)

    def _limit_strain(self, x: torch.Tensor, v: torch.Tensor, limit: torch.Tensor, h: float):
        """``strain_iterations`` Jacobi passes of strain limiting (the module docstring), op by op."""
        receiver, sender = self.edges[:, 0].long(), self.edges[:, 1].long()
        free = torch.ones(x.shape[0], device=x.device, dtype=x.dtype).index_fill(0, self.attached, 0.0)
        share = torch.where(free.index_select(0, sender) > 0, 0.5, 1.0).to(x.dtype)
        for _ in range(self.strain_iterations):
            delta = x.index_select(0, sender) - x.index_select(0, receiver)
            length = delta.norm(dim=1)
            excess = torch.where((limit > 0) & (length > limit), length - limit, 0.0)
            scale = share * excess / length.clamp_min(1e-12)
            move = torch.zeros_like(x).index_add(0, receiver, scale[:, None] * delta)
            weight = torch.minimum(excess / (STRAIN_RAMP * limit).clamp_min(1e-12), torch.ones_like(excess))
            count = torch.zeros_like(free).index_add(0, receiver, weight)
            move = move * (free / count.clamp_min(1.0))[:, None]
            x = x + move
            v = v + move / h
        return x, v

    def _coefficients(self, extra_drag: float):
        """Node masses ``[M]``; per directed edge stiffness, rest length and damping ``[E]``; node drag ``[M]``."""
        mass = self.masses()
        drag = self.drag()
        if extra_drag:
            drag = drag + float(extra_drag) * self.drag_bound
        return (mass, self.stiffness().index_select(0, self.pair_of_edge),
                self.rest_lengths().index_select(0, self.pair_of_edge),
                self.edge_damping().index_select(0, self.pair_of_edge), drag)

    def _constant_force(self, mass: torch.Tensor, external_acceleration: torch.Tensor | None) -> torch.Tensor:
        """Gravity plus the bounded external acceleration, times the mass [N], ``[M, 3]``."""
        force = mass[:, None] * self.gravity
        if external_acceleration is not None:
            force = force + mass[:, None] * self.bounded_acceleration(external_acceleration)
        return force

    def _frame_kernel_inputs(self, extra_drag: float) -> ClothFrame:
        """The fused frame's per-model inputs, made again only when a parameter or buffer changed."""
        # (a ClothModel has no submodules: its own tensors are all of them; read directly, as this runs per frame)
        key = tuple((t.data_ptr(), t._version) for t in (*self._parameters.values(), *self._buffers.values()))
        if getattr(self, "_frame_key", None) != key:
            self._frame_key, self._frames = key, {}
        frame = self._frames.get(extra_drag)
        if frame is None:
            with torch.no_grad():
                mass, stiffness, rest_length, edge_damping, drag = self._coefficients(extra_drag)
                frame = self._frames[extra_drag] = ClothFrame(
                    self.edges, self.edge_row_start, stiffness, rest_length, edge_damping, drag, mass,
                    self._constant_force(mass, None), self.attached,
                    limit_length=self.strain_limits() if self.strain_iterations else None,
                    strain_iterations=self.strain_iterations)
        return frame

    def _fused_frame(self, state, attachment_targets, frame_interval, substeps, capsules, previous_capsules,
                     external_acceleration, extra_drag) -> ClothState:
        frame = self._frame_kernel_inputs(float(extra_drag))
        force = None
        if external_acceleration is not None:
            with torch.no_grad():
                force = self._constant_force(self.masses(), external_acceleration)
        positions, velocities = frame.run(state.positions, state.velocities, attachment_targets, float(frame_interval),
                                          substeps, capsules=_capsule_tensors(capsules),
                                          previous_capsules=_capsule_tensors(previous_capsules),
                                          constant_force=force, cuda_graph=self.frame_cuda_graph)
        return ClothState(positions, velocities)

    @torch.no_grad()
    def settle(
        self,
        state: ClothState,
        attachment_targets: torch.Tensor,
        *,
        capsules: Capsules | None = None,
        frame_interval: float = 1.0 / 30.0,
        max_frames: int = 300,
        kinetic_tolerance: float = 1e-6,
        extra_drag: float = 0.5,
        check_every: int = 10,
    ) -> tuple[ClothState, int]:
        """Let the cloth come to rest in one pose: frames with extra drag until it is still, or ``max_frames``.

        Args:
            state: the starting state (e.g. :meth:`rest_state` of the rest shape).
            attachment_targets: the pose's attachment targets ``[A, 3]`` (held from the first frame on).
            capsules: the pose's capsules.
            frame_interval: duration of one settling frame [s].
            max_frames: at most this many frames.
            kinetic_tolerance: stop once the mean kinetic energy per unit mass of the nodes,
                ``mean(|v|^2) / 2``, is below this [world units^2 / s^2] (checked every ``check_every`` frames:
                a host synchronization each time).
            extra_drag: drag added while settling, as a fraction of its bound.

        Returns:
            ``(state, frames)``: the settled state (velocities kept) and the number of frames run.
        """
        frames = 0
        while frames < max_frames:
            state = self.step(state, attachment_targets, frame_interval, capsules=capsules, extra_drag=extra_drag)
            frames += 1
            if frames % check_every == 0 or frames == max_frames:
                if 0.5 * float((state.velocities**2).sum(dim=1).mean()) < kinetic_tolerance:
                    break
        return state, frames

    def energy(self, state: ClothState) -> torch.Tensor:
        """Kinetic + spring + gravitational energy [J] (springs as ``k (|d| - L)^2 / 2`` per pair)."""
        mass = self.masses()
        x, v = state.positions, state.velocities
        kinetic = 0.5 * (mass * (v * v).sum(dim=1)).sum()
        length = (x[self.pairs[:, 0]] - x[self.pairs[:, 1]]).norm(dim=1)
        spring = 0.5 * (self.stiffness() * (length - self.rest_lengths()) ** 2).sum()
        potential = -(mass[:, None] * x * self.gravity).sum()
        return kinetic + spring + potential


def _capsule_tensors(capsules: Capsules | None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None:
    return None if capsules is None else (capsules.segment_start, capsules.segment_end, capsules.radius)


def _interpolate(before: Capsules, after: Capsules, fraction: float) -> Capsules:
    def mix(a, b):
        return a + fraction * (b - a)

    return Capsules(mix(before.segment_start, after.segment_start), mix(before.segment_end, after.segment_end),
                    mix(before.radius, after.radius))
