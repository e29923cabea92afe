"""Cloth benchmark: ``python tools/bench_kernels.py cloth [--device cuda:0] [--quick]``.

Garment: M = 300 (the cesium skirt's size), 1k, 10k, 100k nodes (``--quick``: 300, 1k) on a tube of radius
0.17 m and height 0.6 m (a shirt around the torso), in grid order (as voxel downsampling leaves neighbours with
nearby ids), its top ring attached; :func:`warpavatar.sim.cloth_graph` with 8 neighbours and 6 second-ring
edges per node. Body: 20 capsules (a torso capsule inside the tube and 19 limb capsules around it), so every
node tests every capsule. One frame is 1/30 s at the default ``max_substep`` 1/240 s: 8 substeps, each (op by
op) a rest-offset and damping pass, one ``spring_step``, the attachment and one ``push_out_of_capsules``, with
the velocity correction; fused, one kernel launch.

Rows time, per call (median):

* ``cloth frame forward``: :meth:`ClothModel.step` under ``torch.no_grad``, op by op (``fused=False``);
* ``cloth frame fused``: the same frame fused, one kernel launch per substep (``fused=True``, what every
  rollout without gradients runs: playing the cloth), and on CUDA ``cloth frame fused, CUDA graph``, its
  launches replayed as one CUDA graph (``ClothModel.frame_cuda_graph``);
* ``cloth frame forward+backward``: the step with autograd, then the gradient of a loss of the final state
  with respect to every parameter and the initial state (the cost of one frame of training);
* ``cloth frame forward, CUDA graph`` (CUDA only): the op-by-op frame captured once into a CUDA graph and
  replayed. The step has static shapes and no host synchronization, so a whole frame (8 substeps, about 30
  small kernels each) replays as one launch: what playing the cloth costs once launch overhead is gone. If
  capture fails the row says so instead of a time;
* ``push_out_of_capsules`` forward and backward alone, for the 20 capsules.

On a CPU shared with other work, ``OMP_NUM_THREADS=1`` keeps torch's thread pool from spinning against it (on
a loaded 2-core machine two threads made a 1k-node frame 100 times slower); the ``threads`` column says what
torch used.
"""

from __future__ import annotations

import math

import torch

from bench_common import time_function

from warpavatar import ops
from warpavatar.sim import Capsules, ClothModel, ClothState, cloth_graph

__all__ = ["run", "make_garment"]

FRAME_INTERVAL = 1.0 / 30.0


def make_garment(node_count: int, device: str, *, seed: int = 0):
    """A tube garment of about ``node_count`` nodes with its top ring attached, and 20 body capsules."""
    generator = torch.Generator().manual_seed(seed)
    radius, height = 0.17, 0.6
    spacing = math.sqrt(2 * math.pi * radius * height / node_count)
    columns = max(3, round(2 * math.pi * radius / spacing))
    rows = max(2, round(node_count / columns))
    row, column = torch.meshgrid(torch.arange(rows), torch.arange(columns), indexing="ij")
    angle = 2 * math.pi * column.reshape(-1).float() / columns
    z = 1.5 - height * row.reshape(-1).float() / (rows - 1)
    rest = torch.stack([radius * angle.cos(), radius * angle.sin(), z], dim=1)
    rest = rest + 0.05 * spacing * torch.randn(rest.shape, generator=generator)
    attached = torch.arange(columns)
    rest = rest.to(device)
    model = ClothModel(rest, cloth_graph(rest, neighbours=8, bend_per_node=6), attached.to(device),
                       node_mass=2.0 / rest.shape[0]).to(device)
    start = torch.cat([torch.tensor([[0.0, 0.0, 0.9]]), 0.6 * (torch.rand(19, 3, generator=generator) - 0.5)
                       + torch.tensor([0.0, 0.0, 1.2])])
    end = torch.cat([torch.tensor([[0.0, 0.0, 1.5]]), start[1:] + 0.3 * torch.randn(19, 3, generator=generator)])
    capsule_radius = torch.cat([torch.tensor([0.14]), 0.03 + 0.04 * torch.rand(19, generator=generator)])
    capsules = Capsules(start.to(device), end.to(device), capsule_radius.to(device))
    return model, rest, capsules


def _row(node_count, edge_count, op, ms, substeps):
    return {"nodes": node_count, "directed edges": edge_count, "op": op, "ms": ms,
            "ms per substep": ms / substeps if (substeps and ms is not None) else None,
            "threads": torch.get_num_threads()}


def _graph_row(model, rest, targets, capsules, device, warmup, repeats, node_count, edge_count, substeps):
    """Time one frame captured in a CUDA graph (static input and output tensors, replayed)."""
    label = f"cloth frame forward, CUDA graph ({substeps} substeps)"
    state = ClothState(rest.clone(), torch.zeros_like(rest))
    try:
        with torch.no_grad():
            side = torch.cuda.Stream(device)
            side.wait_stream(torch.cuda.current_stream(device))
            with torch.cuda.stream(side):  # warm-up off the capture: kernels loaded, allocator primed
                for _ in range(3):
                    model.step(state, targets, FRAME_INTERVAL, capsules=capsules, fused=False)
            torch.cuda.current_stream(device).wait_stream(side)
            graph = torch.cuda.CUDAGraph()
            with torch.cuda.graph(graph):
                model.step(state, targets, FRAME_INTERVAL, capsules=capsules, fused=False)
        ms = time_function(graph.replay, device=device, warmup=warmup, repeats=repeats)
    except Exception as error:  # noqa: BLE001 - the row reports why capture failed
        return _row(node_count, edge_count, f"{label}: capture failed ({type(error).__name__}: {error})"[:160], None,
                    None)
    return _row(node_count, edge_count, label, ms, substeps)


def run(device: str, quick: bool) -> list[dict]:
    """Benchmark rows (see the module docstring)."""
    on_cuda = device.startswith("cuda")
    sizes = (300, 1_000) if quick else (300, 1_000, 10_000, 100_000)
    warmup, repeats = (1, 3) if quick else ((5, 30) if on_cuda else (2, 5))
    rows = []
    for node_count in sizes:
        model, rest, capsules = make_garment(node_count, device)
        node_count = rest.shape[0]
        edge_count = model.edges.shape[0]
        substeps = model.substeps(FRAME_INTERVAL)
        targets = rest[model.attached] + torch.tensor([0.01, 0.0, 0.0], device=device)
        state = model.rest_state(rest)

        def frame(state=state, targets=targets, fused=False):
            return model.step(state, targets, FRAME_INTERVAL, capsules=capsules, fused=fused)

        with torch.no_grad():
            forward_ms = time_function(frame, device=device, warmup=warmup, repeats=repeats)
        rows.append(_row(node_count, edge_count, f"cloth frame forward ({substeps} substeps)", forward_ms, substeps))
        for cuda_graph in (False, True) if on_cuda else (False,):
            model.frame_cuda_graph = cuda_graph
            with torch.no_grad():
                fused_ms = time_function(lambda: frame(fused=True), device=device, warmup=warmup, repeats=repeats)
            label = "cloth frame fused" + (", CUDA graph" if cuda_graph else "")
            rows.append(_row(node_count, edge_count, f"{label} ({substeps} substeps)", fused_ms, substeps))
        model.frame_cuda_graph = False

        if on_cuda:
            rows.append(_graph_row(model, rest, targets, capsules, device, warmup, repeats, node_count, edge_count,
                                   substeps))

        leaves = ClothState(rest.clone().requires_grad_(), torch.zeros_like(rest).requires_grad_())
        inputs = [*model.parameters(), leaves.positions, leaves.velocities]

        def train_frame():
            final = model.step(leaves, targets, FRAME_INTERVAL, capsules=capsules)
            loss = (final.positions * final.positions).sum() + final.velocities.sum()
            return torch.autograd.grad(loss, inputs)

        both_ms = time_function(train_frame, device=device, warmup=warmup, repeats=repeats)
        rows.append(_row(node_count, edge_count, f"cloth frame forward+backward ({substeps} substeps)", both_ms,
                         substeps))

        x = rest.clone().requires_grad_()
        with torch.no_grad():
            push_ms = time_function(
                lambda: ops.push_out_of_capsules(x, capsules.segment_start, capsules.segment_end, capsules.radius),
                device=device, warmup=warmup, repeats=repeats)
        pushed = ops.push_out_of_capsules(x, capsules.segment_start, capsules.segment_end, capsules.radius)
        cotangent = torch.randn_like(pushed)
        push_back_ms = time_function(lambda: torch.autograd.grad(pushed, [x], cotangent, retain_graph=True),
                                     device=device, warmup=warmup, repeats=repeats)
        rows.append(_row(node_count, None, "push_out_of_capsules forward (20 capsules)", push_ms, None))
        rows.append(_row(node_count, None, "push_out_of_capsules backward (20 capsules)", push_back_ms, None))
        del model, rest, leaves, inputs, pushed
    return rows
