"""Benchmark of a fitted avatar (``python tools/bench_kernels.py avatar --avatar PATH/avatar.pt --video FOLDER``).

Times, side by side in one run:

* the rasterizer (forward, forward + backward, peak memory) on the avatar's posed and shaded Gaussians (the first
  training frame's pose and camera), at the training size and at 1920x1080 (the camera's intrinsics scaled to
  that width, the principal point re-centred), against ``gsplat.rasterization`` on the same Gaussians when
  gsplat imports (CUDA only); the notes give the pairs sorted, the peaks, what graphs of ``--replay owned`` hold
  between calls and how many timed calls were replayed by address (the default mode);
* the training step (``Trainer.train_step``) at the avatar's Gaussian count, past densification (the steady step),
  eager and replayed from a CUDA graph, with the work of one step counted: Warp launches (``wp.launch`` plus the
  scan and sort of ``warp.utils``), torch operators (each dispatched aten op, about one kernel each on CUDA), host
  reads (aten ``_local_scalar_dense`` = ``.item()`` / ``float(t)`` / ``bool(t)``, ``nonzero``, boolean-mask
  indexing, and ``Tensor.tolist`` of a device tensor; reads of an optimizer's host-side step counts are
  counted apart, as they synchronize nothing), and on CUDA the runtime's kernel launches and synchronizations as the
  torch profiler records them;
* playback at 1920x1080 (:class:`warpavatar.model.playback.Player`: pose + shade + rasterize) in frames per
  second over the training motion, eager and from a CUDA graph (on CUDA once with the per-Gaussian MLP in float16,
  the player's default there, and once in float32: ``Player(mlp_dtype=...)``). FPS is the throughput of a
  sequence: the frames of the motion drawn one after the other (the player's own capacity checks included) with
  one synchronization at the end, timed by CUDA events around the whole sequence, as a player that hands its
  frames on without waiting for each sees it. The notes add each frame's latency alone (the host's work of one
  ``render`` call plus its GPU work, timed by events around one call and a synchronization, median).

Without ``--avatar`` (as ``--quick`` on CPU does) the avatar is the one a fresh fit of the video starts from.
``--video`` defaults to the built-in demo subject. Times are medians (``bench_common.time_function``); the
rasterizer rows time ours and gsplat in ``--rounds`` interleaved rounds (default 2) and show one value or the range
"low-high" over the rounds.
"""

from __future__ import annotations

import collections
import contextlib
import copy
import dataclasses
import itertools
import os
import sys
import tempfile
import time
import traceback

import torch
from torch.utils._python_dispatch import TorchDispatchMode

from bench_common import interleaved_rounds, time_function, value_range
from bench_splat import _count_warp_calls, _gsplat, _measure, _pair_count, _ratio

from warpavatar import data
from warpavatar._src import splat as splat_bridge
from warpavatar.fit import Trainer, load_training_video, preset
from warpavatar.fit.config import FitConfig
from warpavatar.fit.schedule import make_gaussian_optimizer
from warpavatar.model import Avatar
from warpavatar.model.playback import Player

__all__ = ["run", "count_step_work"]

#: a small fit for ``--quick`` (seconds on a CPU)
QUICK_CONFIG = dict(iterations=400, image_scale=0.25, max_train_frames=6, init_points_per_bone=20,
                    init_carve_candidates=4000, init_carve_points=300, sh_degree=1, sh_increase_every=10,
                    grid_cells=16, grid_min_cells=6, field_hidden=16, field_layers=1, field_warmup_steps=0,
                    gaussian_only_steps=0, densify_from=1000, densify_until=1000, pose_correction=True,
                    pose_correction_hidden=16, log_every=1000, checkpoint_every=100000, preview_frames=0)
#: ``--garment``: a garment forced on the fresh avatar (every Gaussian whose weights split slightly, hung from the
#: root joint) from the first step, so that the training step includes the cloth's window; evenly timed frames
#: (8 of the quick fit's), so that the garment step is captured too
GARMENT_CONFIG = dict(garment="auto", garment_from=0, garment_threshold=0.0005, garment_min_fraction=0.01)
GARMENT_QUICK_CONFIG = dict(max_train_frames=8, garment_voxel=0.12, garment_substep=1.0 / 60.0)
SYNC_OPS = ("_local_scalar_dense", "nonzero", "masked_select", "unique", "_unique2")


class _OpCounter(TorchDispatchMode):
    """Counts the aten operators dispatched inside it, and those that read values back to the host."""

    def __init__(self):
        super().__init__()
        self.ops = collections.Counter()
        self.host_reads = 0
        self.optimizer_reads = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        name = func.overloadpacket.__name__
        self.ops[name] += 1
        boolean_index = name == "index" and any(
            isinstance(index, torch.Tensor) and index.dtype == torch.bool for index in (args[1] if len(args) > 1 else ()))
        if name in SYNC_OPS or boolean_index:
            # the step counts of a non-capturable Adam are host tensors: reading them is no device sync
            if name == "_local_scalar_dense" and args[0].device.type == "cpu" and any(
                    f"torch{os.sep}optim{os.sep}" in frame.filename for frame in traceback.extract_stack()):
                self.optimizer_reads += 1
            else:
                self.host_reads += 1
        return func(*args, **(kwargs or {}))


@contextlib.contextmanager
def _count_tolist(counter: dict):
    original = torch.Tensor.tolist

    def tolist(tensor):
        if tensor.device.type != "cpu":  # (on CPU a tensor's values are on the host already)
            counter["tolist"] = counter.get("tolist", 0) + 1
        return original(tensor)

    torch.Tensor.tolist = tolist
    try:
        yield
    finally:
        torch.Tensor.tolist = original


def count_step_work(step, *, device: str, steps: int = 4) -> dict:
    """Per-step averages over ``steps`` calls of ``step()``: ``warp`` launches (with the warp.utils calls),
    ``torch_ops`` (aten operators), ``host_reads`` (see the module docstring), and on CUDA ``cuda_launches`` and
    ``cuda_syncs`` (profiler runtime events)."""
    warp_calls: dict = {}
    reads: dict = {}
    counter = _OpCounter()
    with _count_warp_calls(warp_calls), _count_tolist(reads), counter:
        for _ in range(steps):
            step()
    result = {"warp": (warp_calls.get("launch", 0) + warp_calls.get("utils", 0)) / steps,
              "torch_ops": sum(counter.ops.values()) / steps,
              "host_reads": (counter.host_reads + reads.get("tolist", 0)) / steps,
              "optimizer_reads": counter.optimizer_reads / steps,
              "top_ops": ", ".join(f"{name} {count / steps:g}" for name, count in counter.ops.most_common(6))}
    if device.startswith("cuda"):
        from torch.profiler import ProfilerActivity, profile

        torch.cuda.synchronize(device)
        with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as profiler:
            for _ in range(steps):
                step()
            torch.cuda.synchronize(device)
        names = collections.Counter(event.name for event in profiler.events())
        launches = sum(count for name, count in names.items() if name in ("cudaLaunchKernel", "cuLaunchKernel",
                                                                          "cudaLaunchKernelExC", "cuLaunchKernelEx"))
        syncs = sum(count for name, count in names.items() if name in (
            "cudaStreamSynchronize", "cudaDeviceSynchronize", "cuStreamSynchronize", "cuCtxSynchronize",
            "cudaEventSynchronize", "cudaMemcpy"))
        result.update(cuda_launches=launches / steps, cuda_syncs=(syncs - 1) / steps,  # minus the closing one
                      graph_launches=names.get("cudaGraphLaunch", 0) / steps)
    return result


# --------------------------------------------------------------------------------------------- set-up
def _load(avatar_path, video_path, device: str, quick: bool, garment: bool = False):
    video_path = video_path or data.demo_subject_path() / "train"
    if avatar_path:
        state = torch.load(avatar_path, map_location="cpu", weights_only=True)
        config = FitConfig.from_dict(state["config"]) if state.get("config") else preset("default")
        fitted = Avatar.from_state(state, device=device)
    else:
        config, fitted = preset("quick" if quick else "default", **(QUICK_CONFIG if quick else {})), None
    if quick and fitted is not None:  # a fitted avatar's config on small frames (as many: frame codes)
        config = dataclasses.replace(config, image_scale=min(config.image_scale, 0.25))
    video = load_training_video(video_path, config)
    if garment and fitted is None:
        config = preset("quick" if quick else "default", **{**(QUICK_CONFIG if quick else {}), **GARMENT_CONFIG,
                                                            **(GARMENT_QUICK_CONFIG if quick else {})},
                        garment_attach=video.skeleton.names[0])
    return video, config, fitted


def _steady_trainer(video, config, fitted, device: str, folder: str, *, cuda_graph: str) -> Trainer:
    """A trainer at its steady step (past densification, the field training), with the fitted avatar's
    Gaussians, field and parts when given."""
    trainer = Trainer(video, config, folder, device=device, cuda_graph=cuda_graph)
    if fitted is not None:
        trainer.avatar.gaussians = copy.deepcopy(fitted.gaussians)
        make_gaussian_optimizer(trainer.gaussians, config, extent=trainer.extent)
        trainer.density.reset(trainer.gaussians.count, trainer.device)
        trainer.skinning.field.load_state_dict(fitted.field.state_dict())
        for name, part in trainer.avatar.parts.items():
            if name in fitted.parts:
                part.load_state_dict(fitted.parts[name].state_dict())
        trainer.avatar.shading_origin = fitted.shading_origin
    trainer.step = max(config.densify_until + 1, config.gaussian_only_steps, 0)
    return trainer


def _posed_scene(avatar: Avatar, video, device: str):
    """The avatar's Gaussians posed for the first frame and shaded for its camera, as rasterizer inputs."""
    camera = video.cameras[0]
    with torch.no_grad():
        posed = avatar.pose(torch.as_tensor(video.bone_transforms[0], dtype=torch.float32, device=device))
        world_to_camera = torch.as_tensor(camera.world_to_camera, dtype=torch.float32, device=device)
        colors = avatar.view_colors(posed, world_to_camera, origin=avatar.shading_origin)
    tensors = [posed["means"], posed["quats"], posed["scales"], posed["opacities"], colors]
    return [t.detach().contiguous().clone() for t in tensors], camera


def _camera_at(camera, width: int, height: int, device: str):
    """The camera's intrinsics scaled to ``width`` (principal point re-centred), as a scene dict of bench_splat."""
    K = torch.as_tensor(camera.K, dtype=torch.float32, device=device).clone()
    factor = width / camera.width
    K[0, 0] *= factor
    K[1, 1] *= factor
    K[0, 2], K[1, 2] = (width - 1) / 2, (height - 1) / 2
    return {"K": K, "world_to_camera": torch.as_tensor(camera.world_to_camera, dtype=torch.float32, device=device),
            "width": width, "height": height}


# --------------------------------------------------------------------------------------------- rows
def _raster_rows(avatar, video, device, warmup, repeats, quick, rounds=2) -> list[dict]:
    from warpavatar.ops import rasterize_gaussians

    tensors, camera = _posed_scene(avatar, video, device)
    sizes = [(camera.width, camera.height), (160, 90) if quick else (1920, 1080)]
    rows = []
    for width, height in sizes:
        scene = _camera_at(camera, width, height, device)
        parameters = [t.clone().requires_grad_() for t in tensors]

        def ours():
            return rasterize_gaussians(*parameters, scene["K"], scene["world_to_camera"], width, height)

        splat_bridge._REPLAYS.clear()  # each size alone: no graph of the other size held on
        splat_bridge._PASS_GRAPHS.clear()
        replays_before = splat_bridge._PASS_GRAPHS.replays
        theirs = _gsplat(scene, parameters)
        runs = interleaved_rounds({
            "ours": lambda: _measure(ours, parameters, device, warmup, repeats),
            "gsplat": None if theirs is None else (lambda: _measure(theirs, parameters, device, warmup, repeats)),
        }, rounds)
        address_replays = splat_bridge._PASS_GRAPHS.replays - replays_before
        held = splat_bridge._REPLAYS.held_bytes() / 2**20
        forward_ms, backward_ms, peak = ([run[i] for run in runs["ours"]] for i in range(3))
        notes = f"{tensors[0].shape[0]} Gaussians"
        if peak[0] is not None:  # (CUDA)
            pairs = _pair_count(dict(scene, **dict(zip(("means", "quats", "scales", "opacities", "colors"), tensors))))
            notes += (f"; peak {max(peak):.1f} MiB + {held:.1f} MiB held by the replayed pass's graph; "
                      f"{address_replays} calls replayed by address; {pairs} pairs")
        row = {"measure": "rasterizer fwd / fwd+bwd ms", "size": f"{width}x{height}",
               "ours": _pair_cell(forward_ms, [f + b for f, b in zip(forward_ms, backward_ms)]), "gsplat": None,
               "ratio": None, "notes": notes}
        if theirs is not None:
            g_forward, g_backward, g_peak = ([run[i] for run in runs["gsplat"]] for i in range(3))
            row.update(gsplat=_pair_cell(g_forward, [f + b for f, b in zip(g_forward, g_backward)]),
                       ratio=_pair_cell([_ratio(f, g) for f, g in zip(forward_ms, g_forward)],
                                        [_ratio(f + b, g + h) for f, b, g, h in
                                         zip(forward_ms, backward_ms, g_forward, g_backward)], digits=2))
            row["notes"] += f" (gsplat peak {max(g_peak):.1f} MiB)"
        rows.append(row)
    return rows


def _pair_cell(first: list, second: list, digits: int = 3) -> str:
    """The table cell "first / second", each one value or its range over the rounds."""
    def text(values):
        cell = value_range(values, digits)
        return f"{cell:.{digits}f}" if isinstance(cell, float) else str(cell)
    return f"{text(first)} / {text(second)}"


def _step_row(trainer, video, device, warmup, repeats) -> dict:
    milliseconds = time_function(trainer.train_step, device=device, warmup=warmup, repeats=repeats)
    counts = count_step_work(trainer.train_step, device=device)
    size = f"{video.cameras[0].width}x{video.cameras[0].height}"
    notes = (f"{trainer.gaussians.count} Gaussians, MLPs in {trainer.config.matmul_precision}; per step: "
             f"{counts['warp']:g} Warp launches, {counts['torch_ops']:g} torch ops, "
             f"{counts['host_reads']:g} host reads "
             f"(+{counts['optimizer_reads']:g} of host step counts)")
    if "cuda_launches" in counts:
        notes += (f", {counts['cuda_launches']:g} CUDA kernel launches, {counts['cuda_syncs']:g} syncs, "
                  f"{counts['graph_launches']:g} graph launches")
    if trainer.use_cuda_graph:
        notes += f", {trainer.graph_replays} of the steps replayed"
    garment = trainer.extension("garment")
    if garment is not None and garment.part is not None:
        notes += (f"; garment: {garment.part.node_count} cloth nodes, window {garment.options.garment_window} "
                  f"frames of {garment.part.cloth.substeps(max(trainer.frames.seconds))} substeps"
                  f"{'' if garment.step_capturable(None) else ' (eager: frames unevenly timed)'}")
    return {"measure": f"training step ms ({'CUDA graph' if trainer.use_cuda_graph else 'eager'})", "size": size,
            "ours": milliseconds, "gsplat": None, "ratio": None, "notes": notes + f"; top ops: {counts['top_ops']}"}


def _sequence_ms(draw, *, device: str, frames: int) -> float:
    """Mean milliseconds a frame of ``frames`` calls of ``draw()`` in a row, with one synchronization at the end
    (CUDA events around the whole sequence; wall time on CPU)."""
    if not device.startswith("cuda"):
        start = time.perf_counter()
        for _ in range(frames):
            draw()
        return (time.perf_counter() - start) * 1e3 / frames
    torch.cuda.synchronize(device)
    start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
    start.record()
    for _ in range(frames):
        draw()
    end.record()
    end.synchronize()
    return start.elapsed_time(end) / frames


def _playback_rows(avatar, video, device, repeats, quick, modes=("off",), *, precision: str,
                   mlp_dtypes=(None,)) -> list[dict]:
    width, height = (160, 90) if quick else (1920, 1080)
    scene = _camera_at(video.cameras[0], width, height, device)
    camera = type("Camera", (), scene)
    bones = torch.as_tensor(video.bone_transforms, dtype=torch.float32, device=device)
    rows = []
    for mode, mlp_dtype in itertools.product(modes, mlp_dtypes):
        player = Player(avatar, camera, cuda_graph=mode, matmul_precision=precision, mlp_dtype=mlp_dtype)
        frame = iter(range(10 ** 9))

        def draw():
            player.render(bones[next(frame) % bones.shape[0]])

        frames = max(repeats, 3 if quick else 300)
        try:
            latency = time_function(draw, device=device, warmup=3, repeats=frames)
            milliseconds = _sequence_ms(draw, device=device, frames=frames)
        except Exception as error:  # noqa: BLE001 (a failed CUDA graph capture is a result to report)
            rows.append(_failed_row("playback FPS (CUDA graph)", f"{width}x{height}", error))
            continue
        counts = count_step_work(draw, device=device)
        rows.append({"measure": f"playback FPS ({'CUDA graph' if player.use_graph else 'eager'})",
                     "size": f"{width}x{height}", "ours": 1000.0 / milliseconds, "gsplat": None, "ratio": None,
                     "notes": f"{milliseconds:.3f} ms/frame over {frames} frames in sequence, {latency:.3f} ms one "
                              f"frame alone (MLPs in {precision}, per-Gaussian MLP in "
                              f"{player.mlp_dtype}); per frame: {counts['warp']:g} "
                              f"Warp launches, {counts['torch_ops']:g} torch ops, {counts['host_reads']:g} host reads"
                              + (f", {counts['cuda_syncs']:g} syncs" if "cuda_syncs" in counts else "")})
    return rows


def run(device: str, quick: bool, *, avatar: str | None = None, video: str | None = None,
        garment: bool = False, matmul_precision: str | None = None, rounds: int = 2) -> list[dict]:
    """Benchmark rows (see the module docstring); ``garment``: with a garment forced on the fresh avatar
    (:data:`GARMENT_CONFIG`; a fitted avatar's own config decides); ``matmul_precision``: the MLPs' GEMMs in
    the step and in playback (default: the config's); ``rounds``: the rasterizer rows' interleaved rounds."""
    warmup, repeats = (1, 3) if quick else (5, 20)
    video_folder, config, fitted = _load(avatar, video, device, quick, garment)
    if matmul_precision is not None:
        config = dataclasses.replace(config, matmul_precision=matmul_precision)
    with tempfile.TemporaryDirectory() as folder:
        eager = _steady_trainer(video_folder, config, fitted, device, folder, cuda_graph="off")
        rows = _raster_rows(eager.avatar, video_folder, device, warmup, repeats, quick, rounds)
        rows.append(_step_row(eager, video_folder, device, warmup, repeats))
    rows += _playback_rows(eager.avatar, video_folder, device, repeats, quick, precision=config.matmul_precision)
    if device.startswith("cuda"):  # last: a capture that fails must not cost the rows above
        with tempfile.TemporaryDirectory() as folder:
            graphed = _steady_trainer(video_folder, config, fitted, device, folder, cuda_graph="on")
            try:
                rows.append(_step_row(graphed, video_folder, device, warmup, repeats))
            except Exception as error:  # noqa: BLE001
                rows.append(_failed_row("training step ms (CUDA graph)", "", error))
        rows += _playback_rows(eager.avatar, video_folder, device, repeats, quick, modes=("on",),
                               precision=config.matmul_precision, mlp_dtypes=("float16", "float32"))
    return rows


def _failed_row(measure: str, size: str, error: Exception) -> dict:
    """A row saying that a measurement failed, and why (first line of the error)."""
    reason = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
    return {"measure": measure, "size": size, "ours": None, "gsplat": None, "ratio": None,
            "notes": f"failed: {type(error).__name__}: {reason[:160]}"}

if __name__ == "__main__":
    from bench_common import markdown_table

    print(markdown_table(run("cuda:0" if torch.cuda.is_available() else "cpu", quick="--quick" in sys.argv)))
