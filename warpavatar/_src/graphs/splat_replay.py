"""Rasterizer passes replayed from CUDA graphs: the eager caller's forward without the host's launch work.

An eager forward pass queues about twenty launches and allocations from Python (some 0.8 ms of host time on the
H200, three times the GPU work of a 40k-Gaussian frame), so calls that repeat one shape are host-bound. Once
:data:`REPLAY_AFTER` consecutive calls of one shape (device, image size, Gaussian count, SH degree and
coefficient count) have fitted their speculative capacity, the pass of that capacity is captured into a CUDA
graph whose inputs and outputs are fixed tensors, and later calls of the shape replay it:

1. the inputs (means, quaternions, scales, opacities, colour coefficients, background, intrinsics, pose) are
   copied into the graph's input tensor by one concatenation;
2. the graph replays the fixed-capacity pass (projection, both sorts, tile ranges, compositing), which writes
   its outputs into three flat tensors: the pixels (image, alpha, depth), the per-Gaussian results with the
   status (radii, projected means and opacities, colours and depths, [pair count, flags]) and what only the
   backward reads (conics, tile ranges, final transmittance, last index, sorted ids);
3. each of the three is cloned (one copy each), so the call's outputs are its own, and the status is read
   (the one host synchronization, as in the speculative mode). Non-finite inputs raise. A pass whose pairs
   outgrew the graph's capacity is not used: the caller runs it eagerly with exact buffers, and the graph is
   dropped, to be captured again at the larger capacity once calls fit again.

The results are those of the speculative mode with the graph's capacity, bit for bit (the same kernels on the
same buffers sizes; CUDA's atomic additions aside, which only the backward has). The backward is unchanged.

A graph keeps its inputs, outputs and the pass's scratch space (the sort buffers, in the capture's memory
pool) for as long as it is cached: at most :data:`REPLAYS_KEPT` shapes, the least recently used dropped first,
and none that would hold over :data:`REPLAY_MAX_BYTES` (such a shape stays eager).
A graph whose capacity is over :data:`SHRINK_FACTOR` times what recent calls need is dropped too (its sorts
would pay for empty slots). A failed capture warns once and leaves that shape eager.

On CPU there is no graph: the tests switch the mode on (``_REPLAY_ON_CPU``), and a "replay" then runs the same
fixed-capacity pass on the same fixed tensors, so everything around the graph is checked on every device.
"""

from __future__ import annotations

import math
import warnings
from collections import OrderedDict
from typing import Callable

import torch

__all__ = ["REPLAY_AFTER", "REPLAYS_KEPT", "REPLAY_MAX_BYTES", "SHRINK_FACTOR", "ReplayCache", "held_bytes"]

REPLAY_AFTER = None
"""Consecutive fitting calls of one shape after which its pass is captured (None: never replay)."""

REPLAYS_KEPT = 1
"""Shapes whose graphs are kept per process (each holds its buffers and sort scratch space)."""

REPLAY_MAX_BYTES = 128 << 20
"""The most a shape's graph may hold between calls (:func:`held_bytes`); a larger shape stays eager. Graphs grow
with the Gaussians and their tile pairs, and passes that large are bound by the GPU's work, not the host's, so a
replay saves them little: on an H100 (2026-11-28) 500k Gaussians at 1080p would hold 244 MiB to take the forward
from 1.76-1.96 ms to 1.67, 1M would hold 432 MiB for no gain, where 100k at 1080p holds 93 MiB and goes from
1.34-1.62 ms to 1.01."""

SHRINK_FACTOR = 2.0
"""A graph is dropped when its capacity exceeds this times the capacity recent calls ask for."""

_REPLAY_ON_CPU = False  # CPU has no graphs; the tests set this to run the same path without one


def _layout_words(layout) -> int:
    return sum(math.prod(shape) for _, shape, _ in layout)


def carve(arena: torch.Tensor, layout) -> dict[str, torch.Tensor]:
    """Views of a flat int32 ``arena`` as the named tensors of ``layout`` ((name, shape, dtype), 4-byte dtypes),
    laid end to end."""
    views, offset = {}, 0
    for name, shape, dtype in layout:
        words = math.prod(shape)
        view = arena[offset: offset + words]
        views[name] = (view if dtype == torch.int32 else view.view(dtype)).view(shape)
        offset += words
    return views


def pass_layouts(gaussian_count: int, width: int, height: int, tiles: int, capacity: int) -> tuple:
    """The three flat tensors a replayed pass writes: (pixels, per-Gaussian results, backward-only state), each a
    list of (name, shape, dtype)."""
    n, f32, i32 = gaussian_count, torch.float32, torch.int32
    pixels = [("image", (height, width, 3), f32), ("alpha", (height, width), f32), ("depth", (height, width), f32)]
    results = [("radii", (n, 2), i32), ("xy_opacity", (n, 3), f32), ("color_depth", (n, 4), f32),
               ("status", (2,), i32)]
    backward = [("conics", (n, 3), f32), ("tile_ranges", (tiles, 2), i32),
                ("final_transmittance", (height, width), f32), ("last_index", (height, width), i32),
                ("sorted_ids", (capacity,), i32)]
    return pixels, results, backward


def held_bytes(input_floats: int, gaussian_count: int, width: int, height: int, tiles: int, capacity: int) -> int:
    """Bytes a graph of one shape holds between calls: its fixed input tensor (``input_floats`` float32), its
    three output tensors (:func:`pass_layouts`), and the torch buffers its pass allocates inside the capture
    (prefix sum 4 B and depth sort 24 B a Gaussian, tile keys and ids 16 B a capacity slot), which stay reserved
    in the capture's memory pool. Warp's sort and scan scratch space comes on top."""
    outputs = sum(_layout_words(layout) for layout in pass_layouts(gaussian_count, width, height, tiles, capacity))
    return 4 * (input_floats + outputs) + 4 * (gaussian_count + 2) + 24 * gaussian_count + 16 * capacity


class _Replay:
    """One captured shape: its fixed input tensor, its three output tensors and the graph (or, on CPU, the pass
    to run again)."""

    def __init__(self, inputs, *, capacity: int, width: int, height: int, sh_degree: int, tiles: int, held: int,
                 run_pass: Callable, buffer_type: type):
        self.capacity = capacity
        self.held = held  # :func:`held_bytes` of this shape
        # The fixed tensors are refilled in place by later calls, whatever their mode: never inference tensors
        # (inference_mode(False) turns gradients on, so no_grad within).
        with torch.inference_mode(False), torch.no_grad():
            self._build(inputs, capacity=capacity, width=width, height=height, sh_degree=sh_degree, tiles=tiles,
                        run_pass=run_pass, buffer_type=buffer_type)

    def _build(self, inputs, *, capacity, width, height, sh_degree, tiles, run_pass, buffer_type) -> None:
        means = inputs[0]
        device = means.device
        sizes = [tensor.numel() for tensor in inputs]
        self._inputs = torch.empty(sum(sizes), device=device, dtype=torch.float32)
        static_inputs, offset = [], 0
        for tensor, size in zip(inputs, sizes):
            static_inputs.append(self._inputs[offset: offset + size].view(tensor.shape))
            offset += size
        self._layouts = pass_layouts(means.shape[0], width, height, tiles, capacity)
        self._outputs = [torch.empty(_layout_words(layout), device=device, dtype=torch.int32)
                         for layout in self._layouts]
        self._buffer_type = buffer_type
        self._copy_in(inputs)
        static_buffers = self._buffers(self._outputs)

        def queue():
            run_pass(*static_inputs, width=width, height=height, sh_degree=sh_degree, capacity=capacity,
                     speculative=False, buffers=static_buffers)
            return self._outputs

        if device.type == "cuda":
            from warpavatar._src.graphs.capture import capture_cuda_graph  # noqa: PLC0415 (torch.cuda only here)

            self._graph, _ = capture_cuda_graph(queue, device=device, warmup=1)
            self._replay = self._graph.replay
        else:
            self._graph = None
            self._replay = queue

    def _copy_in(self, inputs) -> None:
        torch.cat([tensor.reshape(-1) for tensor in inputs], out=self._inputs)

    def _buffers(self, outputs):
        views = {}
        for arena, layout in zip(outputs, self._layouts):
            views.update(carve(arena, layout))
        return self._buffer_type(**views)

    def run(self, inputs):
        """Replay on ``inputs``; returns (buffers of the call's own tensors, pair count, input flags)."""
        self._copy_in(inputs)
        self._replay()
        buffers = self._buffers([output.clone() for output in self._outputs])
        count, flags = buffers.status.tolist()  # the one host sync
        return buffers, count, flags


class ReplayCache:
    """The graphs of recent shapes of one process (see the module doc).

    Args:
        run_pass: the rasterizer's pass (``splat.run_pass``), called with the fixed tensors at capture.
        buffer_type: its buffers' type (``splat.PassBuffers``), built from the output views by name.
        tile_grid: ``(width, height) -> (tiles_x, tiles_y)``.
        raise_on_bad_inputs: raises on the status's non-finite-input flags.
    """

    def __init__(self, *, run_pass: Callable, buffer_type: type, tile_grid: Callable,
                 raise_on_bad_inputs: Callable):
        self._run_pass = run_pass
        self._buffer_type = buffer_type
        self._tile_grid = tile_grid
        self._raise_on_bad_inputs = raise_on_bad_inputs
        self._replays: OrderedDict[tuple, _Replay | None] = OrderedDict()  # None: its capture failed
        self._streaks: dict[tuple, int] = {}
        self.captures = 0  # graphs captured so far (for tests and benchmarks)
        self.replays = 0  # passes replayed so far

    @staticmethod
    def _enabled(device: torch.device) -> bool:
        if REPLAY_AFTER is None:
            return False
        if device.type == "cuda":
            return not torch.cuda.is_current_stream_capturing()
        return _REPLAY_ON_CPU

    @staticmethod
    def _key(inputs, width, height, sh_degree) -> tuple:
        means, coefficients = inputs[0], inputs[4]
        return means.device, width, height, means.shape[0], sh_degree, coefficients.shape[1]

    def held_bytes(self) -> int:
        """Bytes the cached graphs hold between calls (:func:`held_bytes` of each)."""
        return sum(replay.held for replay in self._replays.values() if replay is not None)

    def clear(self) -> None:
        """Drop every graph and streak."""
        self._replays.clear()
        self._streaks.clear()

    def run(self, inputs, *, capacity: int, width: int, height: int, sh_degree: int):
        """Replay the pass of ``inputs``' shape if a graph of it is cached and fits.

        Args:
            inputs: the pass's eight input tensors (float32, contiguous).
            capacity: what the speculative mode would guess now.

        Returns:
            ``(buffers, pair_count)``: the replayed pass, or ``(None, pair_count)`` when no graph was used
            (``pair_count`` is then the count a replay found too large for its graph, or None).

        Raises:
            ValueError: the inputs hold non-finite values.
        """
        if not self._enabled(inputs[0].device):
            return None, None
        key = self._key(inputs, width, height, sh_degree)
        replay = self._replays.get(key)
        if replay is None:
            return None, None
        if replay.capacity > SHRINK_FACTOR * capacity:
            del self._replays[key]  # larger than recent calls need (the key fixes every input's shape)
            return None, None
        self._replays.move_to_end(key)
        buffers, count, flags = replay.run(inputs)
        self._raise_on_bad_inputs(flags)
        if count > replay.capacity:  # outgrown: the caller passes it eagerly; capture again once calls fit
            del self._replays[key]
            return None, count
        self.replays += 1
        return buffers, count

    def note_fitting_call(self, inputs, *, capacity: int, width: int, height: int, sh_degree: int) -> None:
        """Count an eager call of ``inputs``' shape whose pairs fitted ``capacity``; capture its graph once
        :data:`REPLAY_AFTER` such calls came in a row."""
        if not self._enabled(inputs[0].device) or not inputs[0].shape[0]:
            return
        key = self._key(inputs, width, height, sh_degree)
        if key in self._replays:
            return
        streak = self._streaks.get(key, 0) + 1
        if streak < REPLAY_AFTER:
            self._streaks = {key: streak}  # only consecutive calls of one shape count
            return
        self._streaks.pop(key, None)
        tiles_x, tiles_y = self._tile_grid(width, height)
        held = held_bytes(sum(tensor.numel() for tensor in inputs), inputs[0].shape[0], width, height,
                          tiles_x * tiles_y, capacity)
        if held > REPLAY_MAX_BYTES:
            self._keep(key, None)  # too large to hold between calls: stays eager
            return
        try:
            replay = _Replay(inputs, capacity=capacity, width=width, height=height, sh_degree=sh_degree,
                             tiles=tiles_x * tiles_y, held=held, run_pass=self._run_pass,
                             buffer_type=self._buffer_type)
            self.captures += 1
        except Exception as error:  # noqa: BLE001 (any failed capture leaves the shape eager)
            warnings.warn(f"rasterizer: capturing a replayable pass failed, this shape stays eager: {error}",
                          RuntimeWarning)
            replay = None
        self._keep(key, replay)

    def _keep(self, key, replay) -> None:
        self._replays[key] = replay
        while len(self._replays) > REPLAYS_KEPT:
            self._replays.popitem(last=False)
