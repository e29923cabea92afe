"""Benchmark of the Gaussian rasterizer (``python tools/bench_kernels.py splat``), against gsplat when importable.

Scenes follow the usual synthetic set-up: means ~ N(0, 0.6) per axis shifted 3 m in front of the camera,
random-normal quaternions, scales U(0.002, 0.022), opacities U(0.05, 0.95), RGB colours U(0, 1); pinhole camera
with fx = fy = 0.9 * width and the principal point at the image centre (gsplat gets cx + 0.5, cy + 0.5, its
pixel-centre convention). Rows: 40k Gaussians at 1024x1024, 100k / 500k / 1M at 1920x1080.

Per row: forward and backward median times (``bench_common.time_function``: warm-up, then the median of 20
repetitions timed with CUDA events), peak memory of one forward + backward above the inputs
(``bench_common.peak_memory_scope``, torch's allocator), the same for ``gsplat.rasterization`` (default
options, render_mode "RGB+D" so that it also computes depth) on the same inputs, and the ratios ours / gsplat.
Ours and gsplat are measured in ``--rounds`` interleaved rounds (default 2; the order reversed every other
round), each round giving its own times and ratios: a cell shows one value, or the range "low-high" over the
rounds.
``launches`` counts the ``wp.launch`` calls of one forward / one backward, plus the ``warp.utils`` scan and
sort calls (each a few CUB kernels; a forward makes one scan and two sorts, by depth and by tile). ``pairs`` is the number of (Gaussian, tile) pairs sorted and walked by the
compositing (ours: the sum of the projection's tile counts; gsplat: the length of its ``isect_ids``).
``replayed calls`` counts our timed calls served by a CUDA graph: by default one keyed by the addresses of the
call's buffers (``warpavatar/_src/graphs/address_graphs.py``: nothing held between calls); with ``--replay owned`` one
holding its own buffers (``warpavatar/_src/graphs/splat_replay.py``), and then ``graph MiB`` is what its graphs hold
between calls (``ReplayCache.held_bytes``: fixed inputs and outputs, and the pass's sort buffers in the capture's
pool). Those exist before the measured call, so ``peak MiB`` is above them; ``peak ratio`` counts them in: (peak +
graph MiB) / gsplat's peak.
"""

from __future__ import annotations

import contextlib
import sys

import torch
import warp as wp

from bench_common import interleaved_rounds, peak_memory_scope, time_function, value_range

from warpavatar._src import splat as splat_bridge
from warpavatar.ops import rasterize_gaussians

__all__ = ["run", "make_scene"]

FULL_SIZES = ((40_000, 1024, 1024), (100_000, 1920, 1080), (500_000, 1920, 1080), (1_000_000, 1920, 1080))
QUICK_SIZES = ((2_000, 128, 128), (5_000, 192, 108))


def make_scene(gaussian_count: int, width: int, height: int, *, device: str, seed: int = 0) -> dict:
    """The benchmark's random scene: float32 tensors on ``device`` and the camera, in warpavatar's conventions."""
    generator = torch.Generator(device=device).manual_seed(seed)

    def uniform(low, high, *shape):
        return low + (high - low) * torch.rand(*shape, generator=generator, device=device)

    means = 0.6 * torch.randn(gaussian_count, 3, generator=generator, device=device)
    means[:, 2] += 3.0
    focal = 0.9 * width
    K = torch.tensor([[focal, 0.0, (width - 1) / 2], [0.0, focal, (height - 1) / 2], [0.0, 0.0, 1.0]], device=device)
    return dict(
        means=means,
        quats=torch.randn(gaussian_count, 4, generator=generator, device=device),
        scales=uniform(0.002, 0.022, gaussian_count, 3),
        opacities=uniform(0.05, 0.95, gaussian_count),
        colors=uniform(0.0, 1.0, gaussian_count, 3),
        K=K,
        world_to_camera=torch.eye(4, device=device),
        width=width,
        height=height,
    )


@contextlib.contextmanager
def _count_warp_calls(counter: dict):
    """Count kernel launches (``wp.launch`` and the reused commands of ``warpavatar.kernels.launch``) and Warp's
    scan and sort calls (through ``warp.utils`` or the rasterizer's direct calls) made inside the block."""
    originals = (wp.launch, wp.Launch.launch, wp.utils.array_scan, wp.utils.radix_sort_pairs,
                 splat_bridge.radix_sort_pairs, splat_bridge.inclusive_scan)

    def counted(name, function, *, unless_recording=False):
        def wrapper(*args, **kwargs):
            if not (unless_recording and kwargs.get("record_cmd")):  # a recorded command counts when launched
                counter[name] = counter.get(name, 0) + 1
            return function(*args, **kwargs)

        return wrapper

    wp.launch = counted("launch", originals[0], unless_recording=True)
    wp.Launch.launch = counted("launch", originals[1])
    wp.utils.array_scan = counted("utils", originals[2])
    wp.utils.radix_sort_pairs = counted("utils", originals[3])
    splat_bridge.radix_sort_pairs = counted("utils", originals[4])
    splat_bridge.inclusive_scan = counted("utils", originals[5])
    try:
        yield counter
    finally:
        (wp.launch, wp.Launch.launch, wp.utils.array_scan, wp.utils.radix_sort_pairs, splat_bridge.radix_sort_pairs,
         splat_bridge.inclusive_scan) = originals


def _ours(scene: dict, parameters: list):
    def forward():
        return rasterize_gaussians(parameters[0], parameters[1], parameters[2], parameters[3], parameters[4],
                                   scene["K"], scene["world_to_camera"], scene["width"], scene["height"])

    return forward


def _gsplat_K(scene: dict) -> torch.Tensor:
    """The intrinsics in gsplat's convention (pixel centres at half-integers)."""
    K = scene["K"].clone()
    K[0, 2] += 0.5
    K[1, 2] += 0.5
    return K


def _gsplat(scene: dict, parameters: list):
    """gsplat's rasterization of the scene as a function of no arguments, or None (CPU, or no gsplat here)."""
    if not scene["K"].is_cuda:
        return None
    try:
        import gsplat
    except Exception:  # not installed, or its CUDA extension cannot build here
        return None
    K = _gsplat_K(scene)

    def forward():
        colors, alphas, _ = gsplat.rasterization(
            parameters[0], parameters[1], parameters[2], parameters[3], parameters[4],
            scene["world_to_camera"][None], K[None], scene["width"], scene["height"], render_mode="RGB+D",
        )
        return colors[0, ..., :3], alphas[0, ..., 0], colors[0, ..., 3]

    return forward


def _measure(forward, parameters: list, device: str, warmup: int, repeats: int) -> tuple[float, float, float | None]:
    """(forward ms, backward ms, peak MiB of one forward + backward)."""
    outputs = forward()
    cotangents = [torch.rand_like(output) for output in outputs]
    forward_ms = time_function(lambda: forward(), device=device, warmup=warmup, repeats=repeats)
    outputs = forward()
    backward_ms = time_function(
        lambda: torch.autograd.grad(outputs, parameters, cotangents, retain_graph=True),
        device=device, warmup=warmup, repeats=repeats,
    )
    del outputs
    with peak_memory_scope(device) as scope:
        torch.autograd.grad(forward(), parameters, cotangents)
    return forward_ms, backward_ms, scope.peak_mib


def _pair_count(scene: dict) -> int:
    """(Gaussian, tile) pairs of our rasterizer on the scene: its projection kernel's tile counts, summed."""
    from warpavatar._src.warp_utils import to_warp
    from warpavatar.kernels import splat as kernels

    n, device = scene["means"].shape[0], scene["means"].device
    xy_opacity, conics = torch.empty(n, 3, device=device), torch.empty(n, 3, device=device)
    color_depth = torch.empty(n, 4, device=device)
    radii = torch.empty(n, 2, device=device, dtype=torch.int32)
    depth_keys = torch.empty(n, device=device)
    records, flags = torch.zeros(n, 2, device=device, dtype=torch.int32), torch.zeros(1, device=device, dtype=torch.int32)
    kernels.launch_project(
        to_warp(scene["means"], wp.vec3), to_warp(scene["quats"], wp.vec4), to_warp(scene["scales"], wp.vec3),
        to_warp(scene["opacities"]), to_warp(scene["colors"].reshape(n, 1, 3), wp.vec3),
        to_warp(scene["K"].reshape(1, 3, 3), wp.mat33), to_warp(scene["world_to_camera"].reshape(1, 4, 4), wp.mat44),
        width=scene["width"], height=scene["height"], sh_degree=-1, used_coefficients=1,
        xy_opacity=to_warp(xy_opacity, wp.vec3), conics=to_warp(conics, wp.vec3),
        color_depth=to_warp(color_depth, wp.vec4), radii=to_warp(radii, wp.vec2i), depth_keys=to_warp(depth_keys),
        depth_order=to_warp(records, wp.vec2i), bad_input_flags=to_warp(flags),
    )
    wp.synchronize_device(to_warp(records).device)
    return int(records[:, 1].sum())  # the records (Gaussian, tile count) of the depth sort


def _gsplat_pair_count(scene: dict) -> int | None:
    try:
        import gsplat
    except Exception:
        return None
    _, _, meta = gsplat.rasterization(
        scene["means"], scene["quats"], scene["scales"], scene["opacities"], scene["colors"],
        scene["world_to_camera"][None], _gsplat_K(scene)[None], scene["width"], scene["height"], render_mode="RGB+D",
    )
    return int(meta["isect_ids"].numel()) if "isect_ids" in meta else None


def _ratio(ours, theirs):
    if ours is None or theirs is None or theirs == 0:
        return None
    return ours / theirs


def run(device: str, quick: bool, *, rounds: int = 2) -> list[dict]:
    """Benchmark rows (see the module docstring); ``quick`` uses tiny scenes and few repetitions; ``rounds``:
    ours and gsplat timed that many times each, interleaved (:func:`bench_common.interleaved_rounds`)."""
    sizes = QUICK_SIZES if quick else FULL_SIZES
    warmup, repeats = (1, 3) if quick else (5, 20)
    rows = []
    for gaussian_count, width, height in sizes:
        scene = make_scene(gaussian_count, width, height, device=device)
        parameters = [scene[name].clone().requires_grad_() for name in ("means", "quats", "scales", "opacities", "colors")]
        ours = _ours(scene, parameters)

        counter: dict = {}
        with _count_warp_calls(counter):
            outputs = ours()
        forward_calls = dict(counter)
        counter.clear()
        with _count_warp_calls(counter):
            torch.autograd.grad(outputs, parameters, [torch.ones_like(output) for output in outputs])
        backward_calls = dict(counter)
        del outputs

        theirs = _gsplat(scene, parameters)
        replays_before = splat_bridge._REPLAYS.replays + splat_bridge._PASS_GRAPHS.replays
        runs = interleaved_rounds({
            "ours": lambda: _measure(ours, parameters, device, warmup, repeats),
            "gsplat": None if theirs is None else (lambda: _measure(theirs, parameters, device, warmup, repeats)),
        }, rounds)
        held = splat_bridge._REPLAYS.held_bytes() / 2**20
        forward_ms, backward_ms, peak = ([run[i] for run in runs["ours"]] for i in range(3))
        row = {
            "gaussians": gaussian_count,
            "resolution": f"{width}x{height}",
            "fwd ms": value_range(forward_ms),
            "bwd ms": value_range(backward_ms),
            "peak MiB": value_range(peak),
            "launches fwd/bwd": (f"{forward_calls.get('launch', 0)}+{forward_calls.get('utils', 0)} utils / "
                                 f"{backward_calls.get('launch', 0)}"),
            "replayed calls": splat_bridge._REPLAYS.replays + splat_bridge._PASS_GRAPHS.replays - replays_before,
            "graph MiB": held,
            "pairs": _pair_count(scene),
            "gsplat pairs": None,
            "gsplat fwd ms": None,
            "gsplat bwd ms": None,
            "gsplat peak MiB": None,
            "fwd ratio": None,
            "bwd ratio": None,
            "fwd+bwd ratio": None,
            "peak ratio": None,
        }
        if theirs is not None:
            g_forward, g_backward, g_peak = ([run[i] for run in runs["gsplat"]] for i in range(3))
            pairs_of_rounds = list(zip(forward_ms, backward_ms, peak, g_forward, g_backward, g_peak))
            row.update({
                "gsplat pairs": _gsplat_pair_count(scene),
                "gsplat fwd ms": value_range(g_forward),
                "gsplat bwd ms": value_range(g_backward),
                "gsplat peak MiB": value_range(g_peak),
                "fwd ratio": value_range([_ratio(f, gf) for f, _, _, gf, _, _ in pairs_of_rounds]),
                "bwd ratio": value_range([_ratio(b, gb) for _, b, _, _, gb, _ in pairs_of_rounds]),
                "fwd+bwd ratio": value_range([_ratio(f + b, gf + gb) for f, b, _, gf, gb, _ in pairs_of_rounds]),
                "peak ratio": value_range([_ratio(None if p is None else p + held, gp)
                                           for _, _, p, _, _, gp in pairs_of_rounds]),
            })
        rows.append(row)
        del scene, parameters
        splat_bridge._REPLAYS.clear()  # each row alone: no graph of an earlier row's shape held on
        splat_bridge._PASS_GRAPHS.clear()
        if device.startswith("cuda"):
            torch.cuda.empty_cache()
    return rows


if __name__ == "__main__":
    from bench_common import markdown_table

    print(markdown_table(run("cuda:0" if torch.cuda.is_available() else "cpu", quick="--quick" in sys.argv)))
