"""SMAD dynamics benchmark: ``python tools/bench_kernels.py dynamics [--device cuda:0] [--quick]``.

A :class:`warpavatar.extensions.dynamics.SecondaryDynamics` of M = 500, 1500, 5000 nodes (``--quick``: 500) on random
points in a unit box, 19 bones, default network sizes (hidden 64, 3 message passes, 2 substeps), driven by a
100-frame motion. Rows time:

* ``rollout``: one frame of :meth:`~warpavatar.extensions.dynamics.SecondaryDynamics.rollout` without gradients (what a
  refresh of the training cache, ``warpavatar-eval`` and ``warpavatar-animate`` pay per frame);
* ``training window``: the trainer's step of the dynamics, 4 frames rolled with gradients then the backward
  pass of a loss on the last state.

Times are the mean of 10 calls after 3 warm-up calls (``--quick``: 3 after 1). Both are dominated by the
number of small launches (about 110 top-level torch operations and 4 Warp launches per frame forward), not
by M.
"""

from __future__ import annotations

import time

import torch

from warpavatar.extensions.dynamics import SecondaryDynamics
from warpavatar.model import frame_intervals

__all__ = ["run"]

BONES = 19
FRAMES = 100
WINDOW = 4


def _synchronize(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize(torch.device(device))


def _mean_ms(function, device: str, warmup: int, repeats: int) -> float:
    for _ in range(warmup):
        function()
    _synchronize(device)
    start = time.perf_counter()
    for _ in range(repeats):
        function()
    _synchronize(device)
    return (time.perf_counter() - start) / repeats * 1e3


def run(device: str, quick: bool) -> list[dict]:
    """Benchmark rows (see the module docstring)."""
    sizes = (500,) if quick else (500, 1500, 5000)
    warmup, repeats = (1, 3) if quick else (3, 10)
    generator = torch.Generator().manual_seed(0)
    rows = []
    for node_count in sizes:
        nodes = torch.rand(node_count, 3, generator=generator).to(device)
        weights = torch.softmax(3.0 * torch.randn(node_count, BONES, generator=generator), dim=1).to(device)
        dynamics = SecondaryDynamics(nodes, weights, [-1] + list(range(BONES - 1)), voxel_size=0.05,
                                     frame_interval=1.0 / 30.0)
        poses = torch.eye(4, device=device).repeat(FRAMES, BONES, 1, 1)
        poses[:, :, 0, 3] = torch.linspace(0.0, 1.0, FRAMES, device=device)[:, None] ** 2
        intervals = frame_intervals(torch.arange(FRAMES), 30.0).to(device)
        drive = dynamics.drive(poses, intervals)
        seconds = intervals.tolist()

        def window():
            state = dynamics.rest_state()
            for frame in range(50, 50 + WINDOW):
                state = dynamics.step(state, drive, frame, seconds[frame])
            (state.displacement.square().sum() + dynamics.damping(state)).backward()

        rollout_ms = _mean_ms(lambda: dynamics.rollout(poses, intervals), device, 1, max(1, repeats // 5))
        rows.append({"nodes": node_count, "edges": int(dynamics.edges.shape[0]), "what": "rollout, per frame",
                     "ms": round(rollout_ms / (FRAMES - 1), 2)})
        rows.append({"nodes": node_count, "edges": int(dynamics.edges.shape[0]),
                     "what": f"training window ({WINDOW} frames, forward + backward)",
                     "ms": round(_mean_ms(window, device, warmup, repeats), 2)})
    return rows
