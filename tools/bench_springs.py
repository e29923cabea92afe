"""Mass-spring-damper benchmark: ``python tools/bench_kernels.py springs [--device cuda:0] [--quick]``.

Graph: M = 10k, 100k, 1M nodes (``--quick``: 1k, 10k) on a noisy unit sphere, numbered in voxel order (as
voxel-grid downsampling leaves them, so neighbours have nearby ids), with k = 16 directed edges per node
from :func:`warpavatar.ops.knn_graph`, sorted by receiver, int32 ids. Rows time, per call (median):

* ``spring_step`` forward (``torch.no_grad``) and backward (``torch.autograd.grad`` of both outputs with
  respect to all seven float inputs, graph retained, so only the backward kernels are timed), and the same
  for the plain-torch reference;
* ``isometry_loss`` and ``damping_loss`` (velocities of 8 frames), forward and backward.

``GB/s`` is the effective bandwidth: bytes that the kernels must move at least (each array element read
or written once per kernel that touches it; atomics count a read and a write) over the time. On CUDA,
``of_3.0TB/s`` is that over 3.0 TB/s, the H100's measured device-to-device copy bandwidth (bytes read +
written). Byte models (E edges, M nodes, float32, int32 ids):

* step forward: zero-fill 12M; edge kernel edges 8E + rest 12E + stiffness 4E + x 12M + spring-force
  atomics 24M; node kernel reads 56M, writes 24M: ``24E + 128M``;
* step backward: node kernel reads 68M, writes 44M; edge kernel edges 8E + rest 12E + stiffness 4E
  + grad rest 12E + grad stiffness 4E + x 12M + grad force 12M + grad x atomics (receivers and senders)
  48M: ``40E + 184M``;
* isometry forward: edges 8E + rest 12E + x 12M + terms 8E written and summed 8E: ``36E + 12M``;
  backward: edges 8E + rest 12E + grad rest 12E + x 12M + zero-fill and atomics on grad x 36M:
  ``32E + 48M``;
* damping forward over N vectors: 12N + 4N written and summed 4N: ``20N``; backward ``24N``.
"""

from __future__ import annotations


import torch

from bench_common import time_function

from warpavatar import _torch_impl as reference
from warpavatar import ops

__all__ = ["run", "make_system"]

NEIGHBOURS = 16
COPY_BANDWIDTH_GBS = 3000.0
FLOAT_NAMES = ("x", "v", "rest_offset", "stiffness", "damping", "mass", "force")


def make_system(node_count: int, device: str, *, seed: int = 0) -> dict:
    """A spring graph as the avatar uses it: float32 state on ``device``, int32 k-NN edges sorted by receiver."""
    generator = torch.Generator().manual_seed(seed)
    points = torch.randn(node_count, 3, generator=generator)
    points = points / points.norm(dim=1, keepdim=True) + 0.002 * torch.randn(node_count, 3, generator=generator)
    voxel = torch.floor(points / 0.05).long() + 64  # voxel coordinates in [0, 128)
    points = points[torch.argsort((voxel[:, 0] * 256 + voxel[:, 1]) * 256 + voxel[:, 2])]
    points = points.to(device)
    index, _ = ops.knn_graph(points, NEIGHBOURS)
    receiver = torch.arange(node_count, device=device).repeat_interleave(NEIGHBOURS)
    edges = torch.stack([receiver, index.reshape(-1)], dim=1).to(torch.int32).contiguous()
    edge_count = edges.shape[0]

    def rand(*shape, low=0.0, high=1.0):
        return (low + (high - low) * torch.rand(*shape, generator=generator)).to(device)

    rest_offset = (points[edges[:, 0].long()] - points[edges[:, 1].long()]) * rand(edge_count, 1, low=0.9, high=1.1)
    return {
        "x": points + 0.01 * rand(node_count, 3, low=-1.0),
        "v": rand(node_count, 3, low=-1.0),
        "edges": edges,
        "rest_offset": rest_offset,
        "stiffness": rand(edge_count, low=10.0, high=100.0),
        "damping": rand(node_count, low=0.1, high=1.0),
        "mass": rand(node_count, low=0.5, high=2.0),
        "force": rand(node_count, 3, low=-1.0),
    }


def _step(step_fn, system):
    return step_fn(system["x"], system["v"], system["edges"], system["rest_offset"], system["stiffness"],
                   system["damping"], system["mass"], system["force"], 1e-3)


def _row(node_count, edge_count, op, ms, byte_count, on_cuda):
    bandwidth = byte_count / (ms * 1e-3) / 1e9 if byte_count else None
    return {
        "nodes": node_count,
        "edges": edge_count,
        "op": op,
        "ms": ms,
        "GB/s": bandwidth,
        "of_3.0TB/s": (bandwidth / COPY_BANDWIDTH_GBS) if (bandwidth and on_cuda) else None,
    }


def run(device: str, quick: bool) -> list[dict]:
    """Benchmark rows (see the module docstring)."""
    on_cuda = device.startswith("cuda")
    sizes = (1_000, 10_000) if quick else (10_000, 100_000, 1_000_000)
    warmup, repeats = (2, 5) if quick else ((5, 50) if on_cuda else (2, 5))
    rows = []
    for node_count in sizes:
        system = make_system(node_count, device)
        edge_count = system["edges"].shape[0]
        frames = 8

        implementations = (("spring_step", ops.spring_step), ("torch reference spring_step", reference.spring_step))
        for label, step_fn in implementations:
            with torch.no_grad():
                forward_ms = time_function(lambda: _step(step_fn, system), device=device, warmup=warmup,
                                           repeats=repeats)
            leaves = {name: (value.clone().requires_grad_() if name in FLOAT_NAMES else value)
                      for name, value in system.items()}
            outputs = _step(step_fn, leaves)
            cotangents = tuple(torch.randn_like(output) for output in outputs)
            inputs = [leaves[name] for name in FLOAT_NAMES]
            backward_ms = time_function(
                lambda: torch.autograd.grad(outputs, inputs, cotangents, retain_graph=True),
                device=device, warmup=warmup, repeats=repeats,
            )
            rows.append(_row(node_count, edge_count, f"{label} forward", forward_ms,
                             24 * edge_count + 128 * node_count, on_cuda))
            rows.append(_row(node_count, edge_count, f"{label} backward", backward_ms,
                             40 * edge_count + 184 * node_count, on_cuda))
            del outputs, leaves, inputs

        x = system["x"].clone().requires_grad_()
        rest = system["rest_offset"].clone().requires_grad_()
        with torch.no_grad():
            iso_ms = time_function(lambda: ops.isometry_loss(x, system["edges"], rest), device=device,
                                   warmup=warmup, repeats=repeats)
        loss = ops.isometry_loss(x, system["edges"], rest)
        iso_back_ms = time_function(lambda: torch.autograd.grad(loss, [x, rest], retain_graph=True), device=device,
                                    warmup=warmup, repeats=repeats)
        rows.append(_row(node_count, edge_count, "isometry_loss forward", iso_ms,
                         36 * edge_count + 12 * node_count, on_cuda))
        rows.append(_row(node_count, edge_count, "isometry_loss backward", iso_back_ms,
                         32 * edge_count + 48 * node_count, on_cuda))

        velocity = torch.randn(frames, node_count, 3, device=device, requires_grad=True)
        vector_count = frames * node_count
        with torch.no_grad():
            damp_ms = time_function(lambda: ops.damping_loss(velocity), device=device, warmup=warmup, repeats=repeats)
        loss = ops.damping_loss(velocity)
        damp_back_ms = time_function(lambda: torch.autograd.grad(loss, [velocity], retain_graph=True), device=device,
                                     warmup=warmup, repeats=repeats)
        rows.append(_row(node_count, None, f"damping_loss forward ({frames} frames)", damp_ms,
                         20 * vector_count, on_cuda))
        rows.append(_row(node_count, None, f"damping_loss backward ({frames} frames)", damp_back_ms,
                         24 * vector_count, on_cuda))
        del system, loss
    return rows
