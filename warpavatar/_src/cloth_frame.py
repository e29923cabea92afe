"""Torch side of the fused cloth frame (:mod:`warpavatar.kernels.cloth_frame`): no gradients, little host work.

:class:`ClothFrame` holds what stays the same from frame to frame while a cloth's parameters do not change
(the CSR adjacency, the per-edge and per-node coefficients and their Warp views) and the buffers a frame runs
in: the frame's inputs (state, attachment targets, capsules) are copied into fixed tensors, the substeps
ping-pong between two scratch states, so the ``substeps`` kernel launches of a frame are recorded once (per
frame length, substep count and capsule count) and relaunched as they are, or replayed as one CUDA graph. Per
frame the host checks and copies the inputs, relaunches, and returns copies of the final state (new tensors,
so that a caller may keep every state it is given).
"""

from __future__ import annotations

import torch
import warp as wp

from warpavatar._src.graphs.capture import capture_or_fall_back
from warpavatar._src.warp_utils import check_tensor, to_warp, torch_stream_scope
from warpavatar.kernels.cloth_frame import record_cloth_substep, record_strain_limit

__all__ = ["ClothFrame", "csr_rows"]


def csr_rows(receiver: torch.Tensor, node_count: int) -> torch.Tensor:
    """Row offsets int32 ``[M+1]`` of edges sorted by ``receiver`` (int ``[E]``): node ``i``'s edges are
    ``row_start[i]:row_start[i+1]``."""
    bounds = torch.arange(node_count + 1, device=receiver.device, dtype=receiver.dtype)
    return torch.searchsorted(receiver.contiguous(), bounds).to(torch.int32)


class ClothFrame:
    """A cloth's frame without gradients, on the device of its tensors (CPU or CUDA).

    Args:
        edges: directed edges (receiver, sender), integer ``[E, 2]``, sorted by receiver.
        row_start: :func:`csr_rows` of the receivers, int32 ``[M+1]``.
        stiffness, rest_length, edge_damping: float32 ``[E]`` per directed edge [N / world unit, world units,
            N s / world unit].
        drag, mass: float32 ``[M]`` [N s / world unit, kg]; constant_force: float32 ``[M, 3]`` [N].
        attached: ids of the attached nodes, integer ``[A]`` (distinct).
        limit_length: float32 ``[E]`` the longest each directed edge may get after a substep [world units] (0:
            no limit), or None: no strain limiting.
        strain_iterations: Jacobi passes of strain limiting per substep (with ``limit_length``).
    """

    @torch.inference_mode(False)  # (buffers filled in place later, whatever the caller's mode then)
    def __init__(self, edges: torch.Tensor, row_start: torch.Tensor, stiffness: torch.Tensor, rest_length: torch.Tensor,
                 edge_damping: torch.Tensor, drag: torch.Tensor, mass: torch.Tensor, constant_force: torch.Tensor,
                 attached: torch.Tensor, *, limit_length: torch.Tensor | None = None, strain_iterations: int = 0):
        node_count = mass.shape[0]
        device = mass.device
        self.node_count = node_count
        self.device = device
        slot = torch.full((node_count,), -1, dtype=torch.int32, device=device)
        slot[attached.long()] = torch.arange(attached.shape[0], dtype=torch.int32, device=device)
        # the tensors stay referenced here: the Warp views below do not own their memory
        self._tensors = {
            "row_start": row_start.to(torch.int32).contiguous(),
            "neighbour": edges[:, 1].to(torch.int32).contiguous(),
            "stiffness": stiffness.detach().float().contiguous(),
            "rest_length": rest_length.detach().float().contiguous(),
            "edge_damping": edge_damping.detach().float().contiguous(),
            "drag": drag.detach().float().expand(node_count).contiguous(),
            "mass": mass.detach().float().contiguous(),
            "constant_force": constant_force.detach().float().contiguous(),
            "attached_slot": slot,
        }
        self.strain_iterations = int(strain_iterations) if limit_length is not None else 0
        if self.strain_iterations:
            self._tensors["limit_length"] = limit_length.detach().float().contiguous()
        # (no edge: one value, never read)
        for name in ("neighbour", "stiffness", "rest_length", "edge_damping", "limit_length"):
            if edges.shape[0] == 0 and name in self._tensors:
                self._tensors[name] = self._tensors[name].new_zeros(1)
        self._arrays = {name: to_warp(tensor, wp.vec3 if tensor.dim() == 2 else None)
                        for name, tensor in self._tensors.items()}
        # the frame's inputs are copied into these (so the launches never change), the substeps ping-pong
        # between the two scratch states
        self._start = torch.empty(2, node_count, 3, device=device)
        self._attached_count = attached.shape[0]
        self._targets = torch.zeros(max(1, attached.shape[0]), 3, device=device)
        self._scratch = [torch.empty(2, node_count, 3, device=device) for _ in range(2)]
        self._capsules: list[torch.Tensor] = []
        self._launches: list[wp.Launch] = []
        self._launch_key = None
        self._graph = None

    @torch.inference_mode(False)
    def _prepare(self, frame_interval: float, substeps: int, capsule_count: int, constant_force: bool) -> None:
        """Record the frame's launches for these settings (kept while they hold)."""
        key = (frame_interval, substeps, capsule_count, constant_force)
        if key == self._launch_key:
            return
        self._launch_key, self._graph = None, None
        device = self.device
        # segment start, end and radius at the frame's start, then at its end; without capsules one that holds
        # nothing (radius -1: Warp rejects some empty tensors)
        rows = max(1, capsule_count)
        self._capsules = [torch.zeros(rows, 3, device=device) if k % 3 < 2 else torch.full((rows,), -1.0, device=device)
                          for k in range(6)]
        self._force = torch.empty(self.node_count, 3, device=device) if constant_force else None
        vectors = lambda pair: (to_warp(pair[0], wp.vec3), to_warp(pair[1], wp.vec3))  # noqa: E731
        capsules = [to_warp(t, wp.vec3 if t.dim() == 2 else None) for t in self._capsules]
        start = vectors(self._start)
        arrays = self._arrays
        force = arrays["constant_force"] if self._force is None else to_warp(self._force, wp.vec3)
        self._launches = []
        state = start
        launches = 0  # (each launch writes the scratch state the one before did not)
        h = frame_interval / substeps
        for substep in range(1, substeps + 1):
            launches += 1
            out = vectors(self._scratch[launches % 2])
            self._launches.append(record_cloth_substep(
                *state, start[0], arrays["row_start"], arrays["neighbour"], arrays["stiffness"],
                arrays["rest_length"], arrays["edge_damping"], arrays["drag"], arrays["mass"], force,
                arrays["attached_slot"], to_warp(self._targets, wp.vec3), frame_interval, tuple(capsules[:3]),
                tuple(capsules[3:]), substep, substeps, h, *out))
            state = out
            for _ in range(self.strain_iterations):
                launches += 1
                out = vectors(self._scratch[launches % 2])
                self._launches.append(record_strain_limit(*state, arrays["row_start"], arrays["neighbour"],
                                                          arrays["limit_length"], arrays["attached_slot"], h, *out))
                state = out
        self._final = self._scratch[launches % 2]
        self._launch_key = key

    def run(self, positions: torch.Tensor, velocities: torch.Tensor, attachment_targets: torch.Tensor,
            frame_interval: float, substeps: int, *,
            capsules: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None,
            previous_capsules: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None,
            constant_force: torch.Tensor | None = None, cuda_graph: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
        """One frame of ``substeps`` substeps of ``frame_interval / substeps`` seconds.

        Args:
            positions, velocities: the state at the frame's start, float32 ``[M, 3]`` (not modified).
            attachment_targets: the attached nodes' targets at the frame's end, float32 ``[A, 3]``.
            frame_interval: the frame's duration [s].
            substeps: number of substeps (>= 1).
            capsules: ``(segment_start [C,3], segment_end [C,3], radius [C])`` at the frame's end (None: none).
            previous_capsules: the same at the frame's start (None: ``capsules`` all frame long).
            constant_force: float32 ``[M, 3]`` replacing the constant force given at construction (a frame's
                external force).
            cuda_graph: on CUDA, capture the frame's launches once into a CUDA graph and replay it (a failed
                capture warns and goes on without); ignored on CPU.

        Returns:
            ``(positions, velocities)`` at the frame's end, new float32 ``[M, 3]`` tensors.
        """
        node_count = self.node_count
        if node_count == 0:
            return positions.detach().clone(), velocities.detach().clone()
        device = self.device
        check_tensor("positions", positions, (node_count, 3), device=device)
        check_tensor("velocities", velocities, (node_count, 3), device=device)
        check_tensor("attachment_targets", attachment_targets, (self._attached_count, 3), device=device)
        if constant_force is not None:
            check_tensor("constant_force", constant_force, (node_count, 3), device=device)
        capsule_count = 0 if capsules is None else capsules[2].shape[0]
        for prefix, shapes in (("", capsules), ("previous ", previous_capsules)):
            for name, tensor, shape in zip(("segment_start", "segment_end", "radius"), shapes or (),
                                           ((capsule_count, 3), (capsule_count, 3), (capsule_count,))):
                check_tensor(f"{prefix}capsules' {name}", tensor, shape, device=device)
        if capsules is None:  # (as op by op: no capsules, no collision)
            previous_capsules = None
        self._prepare(float(frame_interval), int(substeps), capsule_count, constant_force is not None)
        with torch.no_grad():
            self._start[0].copy_(positions)
            self._start[1].copy_(velocities)
            if attachment_targets.shape[0]:
                self._targets.copy_(attachment_targets)
            if capsule_count:
                before = capsules if previous_capsules is None else previous_capsules
                for buffer, value in zip(self._capsules, (*before, *capsules)):
                    buffer.copy_(value)
            if self._force is not None:
                self._force.copy_(constant_force)
        if cuda_graph and self.device.type == "cuda":
            if self._graph is None:
                captured = capture_or_fall_back(self._launch_all, mode="auto", what="the cloth frame",
                                                device=self.device)
                self._graph = False if captured is None else captured[0]
            if self._graph:
                self._graph.replay()
                return self._final[0].clone(), self._final[1].clone()
        self._launch_all()
        return self._final[0].clone(), self._final[1].clone()

    def _launch_all(self) -> None:
        with torch_stream_scope(self.device):
            for launch in self._launches:
                launch.launch()
