"""A triangle-mesh cloth (a garment sheet) stepped by explicit (semi-implicit) Euler substeps in Warp.

The sheet is a triangle mesh in its rest shape (template-free: any manifold or non-manifold triangle soup with
shared vertices). Its hinges (interior edges, with the two triangles that share them) come from trimesh's face
adjacency; every vertex carries a third of the rest area of its triangles times an areal density [kg/m^2]. Some
vertices are pinned (a waistband ring that follows its joint by skinning): the caller gives their positions per
frame, and within a frame they move on the straight line from where they were to there, with that line's
velocity. The physics is :mod:`warpavatar.kernels.sheet_cloth`: a StVK membrane with a stretch (area) modulus
and a shear modulus [N/m], discrete-shell bending on the dihedral angles [N m], gravity, linear velocity damping
[1/s], aerodynamic drag along each triangle's normal [N s/m^3], and a push out of the body's capsules after every
substep (velocity corrected by the move). Capsules may move within a frame (linear between the frame's first and
last ones).

Stability for any parameter value. Each learned quantity is a squashed logit ``bound * sigmoid(z)``, the bound
fixed at construction for the longest substep ``h <= max_substep``. For semi-implicit Euler on a mode
``x'' = -omega^2 x - gamma x'`` the step is stable while ``h gamma < 2`` and ``h^2 omega^2 < 4 - 2 h gamma`` (the
Jury conditions of its 2x2 step matrix); the bounds keep ``h^2 omega^2 <= 1`` and ``h gamma <= 1``, a factor 2
inside that region:

* stiffness: ``omega^2`` is at most the largest eigenvalue of ``M^-1 K``, ``K`` the Hessian of the elastic
  energy. The membrane's and the bending's Hessians at the rest shape are linear in their stiffness (and
  positive semi-definite there), so :func:`largest_rest_eigenvalue` measures ``lambda_m``, that of the
  membrane with both moduli 1 N/m (a membrane with moduli up to ``k`` has at most ``k lambda_m``), and
  ``lambda_b``, that of the bending at 1 N m, once (power iteration over the free vertices). The bounds are
  ``k_stretch, k_shear <= 0.8 / (h^2 lambda_m)`` and ``k_bend <= 0.2 / (h^2 lambda_b)``, so
  ``h^2 omega^2 <= 0.8 + 0.2`` at rest;
* damping ``c <= 0.5 / h``; the drag's damping rate at a vertex is at most ``k_drag sum_{t at i} A_t / (3 m_i)``
  (``k_drag / rho`` with a uniform density; the normal part of the mean corner velocity, summed over the
  triangles), bounded by ``0.5 / h`` too: ``k_drag <= 0.5 min_i 3 m_i / (h sum_{t at i} A_t)``.

Away from the rest shape the Hessian changes. The membrane stiffens as it stretches, by a factor of about
``1 + 3 E`` at a Green strain ``E``, up to its strain cap of 0.5 (:mod:`warpavatar.kernels.sheet_cloth`), beyond which its stress stops
growing: at most about 2.5 times its rest stiffness at any stretch, within the undamped step's limit of 4, so
collisions and pins that pull the cloth far (even deep initial penetrations of the body) do not make it diverge.
A folded hinge adds ``k w (theta - theta0) hess(theta)``; the bending's share of the budget is small, and a hinge
goes unstable only at about 20 times its bound. The price of an explicit step: the stiffness bound scales with
``rho l^2 / h^2`` (``l`` the edge length), so at a substep of 1/600 s a skirt of 5 cm triangles and 0.2 kg/m^2 is
about 5 N/m stiff and stretches a few per cent under its own weight; stiffer cloth needs a shorter
``max_substep``.

Gradients flow through :func:`warpavatar.ops.sheet_rollout` (one autograd node for a whole window, hand-written
backward) to the five parameters, the initial state, the pin positions and the capsules.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from warpavatar import ops
from warpavatar._src.sheet_cloth import SheetMesh, rest_triangle_frames, sheet_mesh
from warpavatar.sim.mass_spring_cloth import Capsules

__all__ = ["SheetState", "SheetCloth", "sheet_hinges", "vertex_masses", "largest_rest_eigenvalue", "MEMBRANE_SHARE",
           "BEND_SHARE", "DAMPING_SHARE", "DRAG_SHARE"]

MEMBRANE_SHARE = 0.8
"""Part of the stiffness budget ``h^2 omega^2 <= 1`` the membrane may use (the bending uses the rest)."""
BEND_SHARE = 0.2
DAMPING_SHARE = 0.5
"""Part of the damping budget ``1 / h`` the linear damping may use (the drag uses the rest)."""
DRAG_SHARE = 0.5


@dataclass
class SheetState:
    """Positions and velocities of every vertex [m, m/s], ``[V, 3]`` each."""

    positions: torch.Tensor
    velocities: torch.Tensor


def sheet_hinges(faces: torch.Tensor, vertex_count: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The hinges of a triangle mesh: ``(hinges [H, 4], hinge_triangles [H, 2])``, int64.

    A hinge is a pair of triangles sharing an edge (trimesh's ``face_adjacency``): ``(i0, i1)`` the shared edge,
    ``i2`` the other vertex of the first triangle, ``i3`` that of the second. The dihedral angle's sign
    convention (:mod:`warpavatar.kernels.sheet_cloth`) depends on these four points only, not on the triangles'
    winding.
    """
    import trimesh

    faces_np = faces.detach().cpu().numpy().astype(np.int64)
    if faces_np.shape[0] == 0:
        empty = torch.zeros(0, 4, dtype=torch.int64, device=faces.device)
        return empty, empty[:, :2]
    mesh = trimesh.Trimesh(vertices=np.zeros((vertex_count, 3)), faces=faces_np, process=False, validate=False)
    hinges = np.concatenate([mesh.face_adjacency_edges, mesh.face_adjacency_unshared], axis=1)
    return (torch.tensor(hinges, dtype=torch.int64, device=faces.device),
            torch.tensor(np.array(mesh.face_adjacency), dtype=torch.int64, device=faces.device))


def vertex_masses(rest_area: torch.Tensor, faces: torch.Tensor, vertex_count: int, areal_density: float
                  ) -> torch.Tensor:
    """A third of the rest area of each vertex's triangles times ``areal_density`` [kg/m^2]: ``[V]`` [kg]."""
    share = (rest_area.double() * areal_density / 3.0).repeat_interleave(3)
    return torch.zeros(vertex_count, dtype=torch.float64, device=rest_area.device).index_add_(
        0, faces.reshape(-1).long(), share)


def _logit(fraction: float) -> float:
    return math.log(fraction / (1.0 - fraction))


def largest_rest_eigenvalue(mesh: SheetMesh, rest_positions: torch.Tensor, free: torch.Tensor,
                            stretch_stiffness: torch.Tensor,
                            shear_stiffness: torch.Tensor, bend_stiffness: torch.Tensor, *, iterations: int = 200,
                            seed: int = 0) -> float:
    """The largest eigenvalue of ``M^-1 K`` [1/s^2] over the free vertices, ``K`` the Hessian of the sheet's
    energy at its rest shape ``rest_positions [V, 3]`` with the given stiffness arrays (float32 ``[T]``, ``[T]``,
    ``[H]``) and ``free [V]`` marking the vertices that move.

    Power iteration on ``M^-1/2 K M^-1/2`` (symmetric, positive semi-definite at rest), each product ``K u`` the
    gradient of ``<f(x), u>`` through :func:`warpavatar.ops.sheet_forces` (``K`` is minus the force's Jacobian);
    the last Rayleigh quotient, raised by 5 % for what the iterations leave unconverged.
    """
    rest = rest_positions.detach().float().contiguous()
    x = rest.clone().requires_grad_(True)
    zeros = torch.zeros_like(rest)
    drag = torch.zeros_like(stretch_stiffness)
    scale = (mesh.inverse_mass.sqrt() * free.to(torch.float32))[:, None]
    generator = torch.Generator().manual_seed(seed)
    w = (torch.randn(rest.shape, generator=generator).to(rest.device) * scale).double()
    with torch.enable_grad():
        force = ops.sheet_forces(x, zeros, mesh, stretch_stiffness.contiguous(), shear_stiffness.contiguous(),
                                 bend_stiffness.contiguous(), drag.contiguous())
        value = 0.0
        for _ in range(iterations):
            norm = w.norm()
            if not norm > 0:
                return 0.0
            w = w / norm
            (product,) = torch.autograd.grad(force, x, grad_outputs=(scale * w).float(), retain_graph=True)
            w_next = -(scale * product).double()
            value = float((w * w_next).sum())
            w = w_next
    return 1.05 * max(value, 0.0)


class SheetCloth(torch.nn.Module):
    """A garment sheet's learnable physics (stretch, shear, bending, damping, drag), bounded for stability.

    Args:
        rest_positions: vertex positions of the rest shape [m], float ``[V, 3]``.
        faces: vertex ids of each triangle, integer ``[T, 3]``; every vertex must belong to a triangle.
        pinned: ids of the pinned vertices, integer ``[P]`` (their positions come from the caller per frame).
        areal_density: mass per rest area [kg/m^2] (> 0).
        max_substep: longest substep [s]; a frame of ``dt`` seconds takes ``ceil(dt / max_substep)`` substeps.
            The parameters' bounds scale with it (see the module docstring).
        gravity: gravitational acceleration [m/s^2], three numbers; default ``-9.81 * up``.
        up: the world's up direction (skeleton.json's ``up``), used when ``gravity`` is None.
        stretch_stiffness, shear_stiffness, bend_stiffness, damping, drag: initial values as fractions ``(0, 1)``
            of their bounds.

    Raises:
        ValueError: bad shapes, ids out of range, a vertex in no triangle, repeated pins, options out of range.
    """

    def __init__(
        self,
        rest_positions: torch.Tensor,
        faces: torch.Tensor,
        pinned: torch.Tensor,
        *,
        areal_density: float = 0.2,
        max_substep: float = 1.0 / 600.0,
        gravity: tuple[float, float, float] | None = None,
        up: tuple[float, float, float] = (0.0, 0.0, 1.0),
        stretch_stiffness: float = 0.9,
        shear_stiffness: float = 0.5,
        bend_stiffness: float = 0.1,
        damping: float = 0.01,
        drag: float = 0.01,
    ):
        super().__init__()
        if rest_positions.dim() != 2 or rest_positions.shape[1] != 3:
            raise ValueError(f"rest_positions must have shape [V, 3], got {list(rest_positions.shape)}")
        if faces.dim() != 2 or faces.shape[1] != 3 or faces.is_floating_point():
            raise ValueError(f"faces must be integer vertex ids of shape [T, 3], got {faces.dtype} "
                             f"{list(faces.shape)}")
        if not (areal_density > 0 and math.isfinite(areal_density)):
            raise ValueError(f"areal_density must be a positive number [kg/m^2], got {areal_density}")
        if not (max_substep > 0 and math.isfinite(max_substep)):
            raise ValueError(f"max_substep must be a positive number of seconds, got {max_substep}")
        for name, fraction in (("stretch_stiffness", stretch_stiffness), ("shear_stiffness", shear_stiffness),
                               ("bend_stiffness", bend_stiffness), ("damping", damping), ("drag", drag)):
            if not 0.0 < fraction < 1.0:
                raise ValueError(f"{name} is a fraction of its bound and must be in (0, 1), got {fraction}")
        device = rest_positions.device
        rest = rest_positions.detach().double()
        vertex_count = rest.shape[0]
        faces = faces.to(device=device, dtype=torch.int64)
        if faces.numel() and (int(faces.min()) < 0 or int(faces.max()) >= vertex_count):
            raise ValueError(f"faces must hold vertex ids in [0, {vertex_count})")
        used = torch.zeros(vertex_count, dtype=torch.bool, device=device)
        used[faces.reshape(-1)] = True
        if not bool(used.all()):
            raise ValueError(f"{int((~used).sum())} of the {vertex_count} vertices belong to no triangle (they would "
                             "have no mass)")
        pinned = torch.as_tensor(pinned, device=device).reshape(-1).long()
        hinges, hinge_triangles = sheet_hinges(faces, vertex_count)
        _, rest_area = rest_triangle_frames(rest, faces)
        mass = vertex_masses(rest_area, faces, vertex_count, float(areal_density))
        if not bool((mass > 0).all()):
            raise ValueError("every vertex needs a triangle of nonzero rest area (some have no mass)")
        self.mesh: SheetMesh = sheet_mesh(rest, faces, hinges, hinge_triangles, mass, pinned)
        self.max_substep = float(max_substep)
        self.areal_density = float(areal_density)
        if gravity is None:
            up_vector = np.asarray(up, dtype=np.float64)
            gravity = tuple(-9.81 * up_vector / np.linalg.norm(up_vector))
        self.gravity = tuple(float(g) for g in gravity)
        self.register_buffer("rest_positions", rest.float())
        self.register_buffer("faces", faces)
        self.register_buffer("pinned_ids", pinned.clone())  # (with the two above: what rebuilds the sheet)

        bounds = self._bounds(rest, faces, hinges, mass, pinned)
        self.max_membrane_stiffness, self.max_bend_stiffness, self.max_damping, self.max_drag = bounds
        self.stretch_logit = torch.nn.Parameter(torch.tensor(_logit(stretch_stiffness), device=device))
        self.shear_logit = torch.nn.Parameter(torch.tensor(_logit(shear_stiffness), device=device))
        self.bend_logit = torch.nn.Parameter(torch.tensor(_logit(bend_stiffness), device=device))
        self.damping_logit = torch.nn.Parameter(torch.tensor(_logit(damping), device=device))
        self.drag_logit = torch.nn.Parameter(torch.tensor(_logit(drag), device=device))

    def _bounds(self, rest, faces, hinges, mass, pinned) -> tuple[float, float, float, float]:
        """The four bounds of the module docstring: membrane and bending stiffness, damping, drag."""
        h = self.max_substep
        vertex_count = rest.shape[0]
        free = torch.ones(vertex_count, dtype=torch.bool, device=rest.device)
        free[pinned] = False
        if not bool(free.any()):
            return math.inf, math.inf, DAMPING_SHARE / h, math.inf
        triangle_count, hinge_count = self.mesh.triangle_count, self.mesh.hinge_count
        one, zero = rest.new_ones((), dtype=torch.float32), rest.new_zeros((), dtype=torch.float32)
        ones, zeros = one.expand(triangle_count), zero.expand(triangle_count)
        membrane = largest_rest_eigenvalue(self.mesh, rest, free, ones, ones, zero.expand(hinge_count))
        bending = largest_rest_eigenvalue(self.mesh, rest, free, zeros, zeros, one.expand(hinge_count)) \
            if hinge_count else 0.0
        max_membrane = MEMBRANE_SHARE / (h**2 * membrane) if membrane > 0 else math.inf
        max_bend = BEND_SHARE / (h**2 * bending) if bending > 0 else math.inf
        area = self.mesh.rest_area.double()
        drag_area = torch.zeros(vertex_count, dtype=torch.float64, device=rest.device).index_add_(
            0, faces.reshape(-1), (area / 3.0).repeat_interleave(3))
        max_drag = DRAG_SHARE * float((mass / drag_area.clamp_min(1e-300))[free].min()) / h
        return max_membrane, max_bend, DAMPING_SHARE / h, max_drag

    # ------------------------------------------------------------------------------------ bounded values
    @property
    def vertex_count(self) -> int:
        return self.mesh.vertex_count

    @property
    def pinned(self) -> torch.Tensor:
        """Ids of the pinned vertices, int64 ``[P]``."""
        return self.mesh.pinned

    def stretch_stiffness(self) -> torch.Tensor:
        """Area-stretch modulus [N/m], a scalar tensor."""
        return self.max_membrane_stiffness * torch.sigmoid(self.stretch_logit)

    def shear_stiffness(self) -> torch.Tensor:
        """Shear modulus [N/m], a scalar tensor."""
        return self.max_membrane_stiffness * torch.sigmoid(self.shear_logit)

    def bend_stiffness(self) -> torch.Tensor:
        """Bending stiffness [N m], a scalar tensor."""
        return self.max_bend_stiffness * torch.sigmoid(self.bend_logit)

    def damping(self) -> torch.Tensor:
        """Linear velocity damping [1/s], a scalar tensor."""
        return self.max_damping * torch.sigmoid(self.damping_logit)

    def drag(self) -> torch.Tensor:
        """Aerodynamic drag coefficient [N s/m^3], a scalar tensor."""
        return self.max_drag * torch.sigmoid(self.drag_logit)

    def substeps(self, frame_interval: float) -> int:
        """Substeps of a frame of ``frame_interval`` seconds: ``ceil(frame_interval / max_substep)``."""
        return max(1, math.ceil(float(frame_interval) / self.max_substep - 1e-9))

    def rest_state(self) -> SheetState:
        """The rest shape, at rest."""
        return SheetState(self.rest_positions.clone(), torch.zeros_like(self.rest_positions))

    # ---------------------------------------------------------------------------------------- stepping
    def step(self, state: SheetState, pinned_positions: torch.Tensor, frame_interval: float, *,
             capsules: Capsules | None = None, previous_capsules: Capsules | None = None,
             substeps: int | None = None) -> SheetState:
        """Advance the sheet by one frame.

        Args:
            state: the state at the end of the previous frame (pinned vertices where they were).
            pinned_positions: where the pinned vertices are at the end of this frame [m], ``[P, 3]``.
            frame_interval: the frame's duration [s], a Python number > 0.
            capsules: the body's capsules at the end of the frame (None: no collision).
            previous_capsules: the capsules at the start of the frame (None: ``capsules`` all frame long).
            substeps: substeps of the frame (default :meth:`substeps`); more are fine, fewer are refused when
                the substep would exceed ``max_substep`` (the bounds would not hold).

        Returns:
            The state at the end of the frame.
        """
        frame_capsules = None
        if capsules is not None:
            frame_capsules = Capsules(capsules.segment_start[None], capsules.segment_end[None], capsules.radius[None])
        positions, velocities = self.rollout(state, pinned_positions[None], frame_interval, capsules=frame_capsules,
                                             initial_capsules=previous_capsules, substeps=substeps)
        return SheetState(positions[0], velocities[0])

    def rollout(self, state: SheetState, pinned_positions: torch.Tensor, frame_interval: float, *,
                capsules: Capsules | None = None, initial_capsules: Capsules | None = None,
                substeps: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Advance the sheet over ``F`` frames in one differentiable rollout.

        Args:
            state: the state at the start (pinned vertices where they are then).
            pinned_positions: the pinned vertices at the end of every frame [m], ``[F, P, 3]``.
            frame_interval: the frames' duration [s], a Python number > 0.
            capsules: the body's capsules at the end of every frame: a :class:`Capsules` of ``[F, C, 3]``
                segment ends and ``[F, C]`` radii (None: no collision).
            initial_capsules: the capsules at the start (``[C, 3]``, ``[C]``; None: the first frame's).
            substeps: substeps per frame (see :meth:`step`).

        Returns:
            ``(positions [F, V, 3], velocities [F, V, 3])`` at the end of every frame.
        """
        if not (isinstance(frame_interval, (int, float)) and frame_interval > 0 and math.isfinite(frame_interval)):
            raise ValueError(f"frame_interval must be a positive number of seconds, got {frame_interval!r}")
        pinned_count = self.mesh.pinned_count
        if pinned_positions.dim() != 3 or pinned_positions.shape[1:] != (pinned_count, 3):
            raise ValueError(f"pinned_positions must have shape [F, {pinned_count}, 3], got "
                             f"{list(pinned_positions.shape)}")
        default = self.substeps(frame_interval)
        if substeps is None:
            substeps = default
        elif isinstance(substeps, bool) or not isinstance(substeps, int) or substeps < default:
            raise ValueError(f"substeps must be an integer >= {default} (a substep of at most max_substep "
                             f"{self.max_substep:.6g} s), got {substeps!r}")
        h = float(frame_interval) / substeps
        frame_count = pinned_positions.shape[0]
        start = state.positions.index_select(0, self.mesh.pinned)
        keyframes = torch.cat([start[None], pinned_positions.to(start.dtype)])
        pin_targets = _interpolated(keyframes, substeps)
        pin_velocities = ((keyframes[1:] - keyframes[:-1]) / float(frame_interval))[:, None].expand(
            frame_count, substeps, pinned_count, 3).reshape(frame_count * substeps, pinned_count, 3)
        capsule_rows = None
        if capsules is not None:
            first = initial_capsules if initial_capsules is not None else Capsules(
                capsules.segment_start[0], capsules.segment_end[0], capsules.radius[0])
            capsule_rows = tuple(
                _interpolated(torch.cat([before[None], after]), substeps) for before, after in (
                    (first.segment_start, capsules.segment_start), (first.segment_end, capsules.segment_end),
                    (first.radius, capsules.radius)))
        triangle_count, hinge_count = self.mesh.triangle_count, self.mesh.hinge_count
        return ops.sheet_rollout(
            state.positions, state.velocities, self.mesh, self.stretch_stiffness().expand(triangle_count),
            self.shear_stiffness().expand(triangle_count), self.bend_stiffness().expand(hinge_count),
            self.drag().expand(triangle_count), self.damping().expand(self.vertex_count), pin_targets,
            pin_velocities.contiguous(), substep=h, substeps_per_frame=substeps, gravity=self.gravity,
            capsules=capsule_rows)

    def _apply(self, fn, *args, **kwargs):
        # the mesh's tensors move with the module (.to, .cuda)
        result = super()._apply(fn, *args, **kwargs)
        mesh = self.mesh
        self.mesh = SheetMesh(**{name: fn(getattr(mesh, name)) for name in mesh.__dataclass_fields__})
        return result


def _interpolated(keyframes: torch.Tensor, substeps: int) -> torch.Tensor:
    """Values at the end of every substep on straight lines between consecutive ``keyframes [F+1, ...]``:
    ``[F * substeps, ...]`` (each frame's last substep exactly its keyframe)."""
    fraction = torch.arange(1, substeps + 1, dtype=keyframes.dtype, device=keyframes.device) / substeps
    before, after = keyframes[:-1, None], keyframes[1:, None]
    shape = (-1,) + (1,) * (keyframes.dim() - 1)
    values = before + fraction.reshape(1, *shape) * (after - before)
    values = torch.cat([values[:, :-1], after], dim=1)
    return values.reshape(-1, *keyframes.shape[1:]).contiguous()
