"""Skinning micro-benchmarks: ``python tools/bench_kernels.py skinning [--quick] [--device cuda:0]``.

sample_grid: TAGA's skinning field, 64x64x16 samples stored as ``grid[D, H, W, C]`` with
``[D, H, W] = [64, 16, 64]`` (64 samples along z, the body's up axis, 16 along y, its front-to-back depth,
64 along x, its width), C = 24 and 64 channels, N = 1M points, for both thread layouts of the Warp kernels
(``point``: a thread per point looping channels; ``channel``: a thread per (point, channel)), against
``torch.nn.functional.grid_sample``. Backward computes the gradients of both the grid and the points.

lbs: N = 100k and 1M points, J = 24 and 41 bones, with and without quaternions; forward and backward (the
gradients of every input) against the plain-torch reference (without quaternions only: the reference's
batched SVD is not a meaningful baseline). One inverse_lbs row for comparison.

Bandwidth (``fwd_GBps``, ``bwd_GBps``) counts each input read once and each output written once (the
minimal traffic of the op, weights included), divided by the median time: an effective figure to compare
with the device's peak (about 3.3 TB/s on an H100 SXM), not a measured DRAM counter.
"""

from __future__ import annotations

import torch

from bench_common import peak_memory_scope, time_function
from warpavatar import ops
from warpavatar._src import skinning as skinning_src
from warpavatar._torch_impl import skinning as reference

__all__ = ["run"]

FLOAT_BYTES = 4


def _timed_pair(forward, device, repeats):
    """Median forward ms, median backward ms and peak MiB of one forward + backward."""
    with torch.no_grad():
        forward_ms = time_function(lambda: forward(), device=device, repeats=repeats)
    outputs, inputs = forward(record=True)
    cotangents = [torch.randn_like(o) for o in outputs]

    def backward():
        torch.autograd.grad(outputs, inputs, cotangents, retain_graph=True)

    backward_ms = time_function(backward, device=device, repeats=repeats)
    with peak_memory_scope(device) as scope:
        outputs2, inputs2 = forward(record=True)
        torch.autograd.grad(outputs2, inputs2, cotangents)
    return forward_ms, backward_ms, scope.peak_mib


def _bandwidth(byte_count, milliseconds):
    return byte_count / (milliseconds * 1e-3) / 1e9 if milliseconds else None


def _bench_sample_grid(device, quick):
    rows = []
    point_count = 20_000 if quick else 1_000_000
    grid_shape = (16, 4, 16) if quick else (64, 16, 64)
    repeats = 3 if quick else 20
    bbox_min = torch.tensor([-1.0, -0.3, 0.0], device=device)
    bbox_max = torch.tensor([1.0, 0.3, 2.0], device=device)
    generator = torch.Generator(device="cpu").manual_seed(0)
    for channel_count in (24, 64):
        grid = torch.randn(*grid_shape, channel_count, generator=generator).to(device)
        unit = torch.rand(point_count, 3, generator=generator).to(device)
        points = bbox_min + unit * (bbox_max - bbox_min)
        grid_bytes = grid.numel() * FLOAT_BYTES
        forward_bytes = point_count * 3 * FLOAT_BYTES + grid_bytes + point_count * channel_count * FLOAT_BYTES
        backward_bytes = 2 * point_count * 3 * FLOAT_BYTES + point_count * channel_count * FLOAT_BYTES \
            + 2 * grid_bytes
        variants = [("warp/point", "point"), ("warp/channel", "channel"), ("torch grid_sample", None)]
        for name, layout in variants:
            saved = dict(skinning_src._SAMPLE_GRID_LAYOUT)
            if layout is not None:
                skinning_src._SAMPLE_GRID_LAYOUT.update(cpu=layout, cuda=layout)
            function = ops.sample_grid if layout is not None else reference.sample_grid

            def forward(record=False, function=function, grid=grid, points=points):
                if record:
                    inputs = (grid.detach().requires_grad_(True), points.detach().requires_grad_(True))
                    return [function(*inputs, bbox_min, bbox_max)], inputs
                return function(grid, points, bbox_min, bbox_max)

            try:
                forward_ms, backward_ms, peak = _timed_pair(forward, device, repeats)
            finally:
                skinning_src._SAMPLE_GRID_LAYOUT.update(saved)
            rows.append({
                "op": "sample_grid", "impl": name, "N": point_count,
                "shape": f"{'x'.join(map(str, grid_shape))}x{channel_count}", "quats": "-",
                "fwd_ms": forward_ms, "bwd_ms": backward_ms,
                "fwd_GBps": _bandwidth(forward_bytes, forward_ms), "bwd_GBps": _bandwidth(backward_bytes, backward_ms),
                "peak_MiB": peak,
            })
    return rows


def _random_bones(bone_count, generator):
    bones = torch.eye(4).repeat(bone_count, 1, 1)
    q = torch.randn(bone_count, 4, generator=generator)
    q = q / q.norm(dim=1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    bones[:, :3, :3] = torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1).view(-1, 3, 3)
    bones[:, :3, 3] = 0.3 * torch.randn(bone_count, 3, generator=generator)
    return bones


def _bench_lbs(device, quick):
    rows = []
    repeats = 3 if quick else 20
    sizes = (2_000, 20_000) if quick else (100_000, 1_000_000)
    generator = torch.Generator(device="cpu").manual_seed(1)
    configs = [(op_name, n, j, q) for n in sizes for j in (24, 41) for q in (False, True) for op_name in ("lbs",)]
    configs.append(("inverse_lbs", sizes[-1], 24, True))
    for op_name, point_count, bone_count, with_quats in configs:
        points = torch.randn(point_count, 3, generator=generator).to(device)
        # sparse-ish skinning: a few dominant bones per point, stored densely as TAGA does
        logits = 4.0 * torch.randn(point_count, bone_count, generator=generator)
        weights = torch.softmax(logits, dim=1).to(device)
        bones = _random_bones(bone_count, generator).to(device)
        quats = torch.randn(point_count, 4, generator=generator).to(device) if with_quats else None
        point_bytes = point_count * 3 * FLOAT_BYTES
        weight_bytes = point_count * bone_count * FLOAT_BYTES
        quat_bytes = point_count * 4 * FLOAT_BYTES if with_quats else 0
        forward_bytes = 2 * point_bytes + weight_bytes + 2 * quat_bytes
        # reads: the inputs and the outputs' cotangents; writes: the gradient of every input
        backward_bytes = 3 * point_bytes + 2 * weight_bytes + 3 * quat_bytes
        implementations = [("warp", getattr(ops, op_name))]
        if not with_quats:
            implementations.append(("torch reference", getattr(reference, op_name)))
        for impl_name, function in implementations:

            def forward(record=False, function=function, points=points, weights=weights, bones=bones, quats=quats):
                if record:
                    inputs = [x.detach().requires_grad_(True) for x in (points, weights, bones)]
                    if quats is not None:
                        inputs.append(quats.detach().requires_grad_(True))
                    outputs = function(*inputs[:3], quats=inputs[3] if quats is not None else None)
                    return [o for o in outputs if o is not None], inputs
                return function(points, weights, bones, quats=quats)

            forward_ms, backward_ms, peak = _timed_pair(forward, device, repeats)
            rows.append({
                "op": op_name, "impl": impl_name, "N": point_count, "shape": f"J={bone_count}",
                "quats": "yes" if with_quats else "no",
                "fwd_ms": forward_ms, "bwd_ms": backward_ms,
                "fwd_GBps": _bandwidth(forward_bytes, forward_ms), "bwd_GBps": _bandwidth(backward_bytes, backward_ms),
                "peak_MiB": peak,
            })
    return rows


def run(device: str, quick: bool) -> list[dict]:
    """Benchmark rows of sample_grid and lbs on ``device`` (small sizes and few repeats when ``quick``)."""
    return _bench_sample_grid(device, quick) + _bench_lbs(device, quick)
