"""CUDA graphs of a queue of work keyed by the addresses it touches: a repeated call's launches without their host
cost, and without memory of their own.

A rasterizer pass at avatar scale takes less GPU time than the host needs to queue its launches (issue #18), and
a graph that owns its buffers (:mod:`warpavatar._src.graphs.splat_replay`) doubles the pass's memory on small images
(``docs/rasterizer_memory.md``). The work of one call is fixed by its kernels' arguments: the addresses of the
buffers it reads and writes, their sizes and a few scalars. Callers that allocate the same buffers in the same
order call after call get the same addresses back from torch's caching allocator. So :class:`AddressKeyedGraphs`
takes a key naming all of that (the caller builds it: every address and size the work touches, and every scalar
that its launches take) and a function that queues the work:

* a key seen for the :data:`CAPTURE_AFTER`-th time in the recent past is captured: the function runs once under
  a CUDA stream capture on a side stream (nothing executes; the launches are recorded with their addresses), and
  the graph is launched on torch's current stream;
* a key with a graph replays it: one graph launch on torch's current stream instead of the function's launches;
* any other key runs the function eagerly.

The graph holds no tensor: its addresses belong to the caller's tensors of the current call, allocated before
the work is queued and alive until it is (as for an eager launch, stream order does the rest). Between calls the
addresses may serve other tensors; a graph only runs when the current call's buffers have exactly those
addresses again, so what it touches is what the eager launches would. Warp's sort and scan allocate their
scratch space inside the graph (CUDA graph allocations, freed within it), which is all the memory a graph keeps,
outside torch's allocator. At most :data:`GRAPHS_KEPT` graphs are kept, the least recently used dropped first.

The function must not read from the device, allocate (its buffers are the key's) or hold references beyond the
call, and its work must depend on nothing but the key. A failed capture warns once, and that key runs eagerly
from then on. On CPU there is no graph: the function always runs eagerly.
"""

from __future__ import annotations

import ctypes
import warnings
from collections import OrderedDict
from typing import Callable

import torch
import warp as wp

from warpavatar._src.warp_utils import (current_stream_handle, init_warp, native_entry, torch_stream_scope,
                                        warp_stream_of)

__all__ = ["CAPTURE_AFTER", "DEFAULT_CAPTURE_AFTER", "GRAPHS_KEPT", "AddressKeyedGraphs"]

DEFAULT_CAPTURE_AFTER = 2
"""A key is captured when seen this many times among the last :data:`_RECENT_KEYS` keys."""

CAPTURE_AFTER: int | None = DEFAULT_CAPTURE_AFTER
"""The setting in force (None: never capture, every call eager; ``warpavatar.ops.rasterizer_replays`` sets it)."""

GRAPHS_KEPT = 8
"""Graphs kept per :class:`AddressKeyedGraphs` (each holds only its launches and its sort scratch space)."""

_RECENT_KEYS = 64  # distinct keys counted before the count starts over


def _launch(graph, device: torch.device) -> None:
    """Launch ``graph`` on torch's current stream of ``device``: through Warp the first time (which instantiates
    it), then through Warp's native entry point with the stream's handle (what ``wp.capture_launch`` ends in,
    without its checks and the stream wrapper's lookup)."""
    launch = native_entry("wp_cuda_graph_launch")  # (graph_exec, stream)
    if graph.graph_exec is None or launch is None:
        wp.capture_launch(graph, stream=warp_stream_of(torch.cuda.current_stream(device)))
        return
    if not launch(graph.graph_exec, ctypes.c_void_p(current_stream_handle(device))):
        raise RuntimeError("launching a CUDA graph of a repeated call failed")


class AddressKeyedGraphs:
    """The graphs of recently repeated keys (see the module doc).

    Attributes:
        captures: graphs captured so far; ``replays``: calls served by a graph; ``eager``: calls run eagerly
            (for tests and benchmarks).
    """

    def __init__(self):
        self._graphs: OrderedDict[tuple, object] = OrderedDict()  # key -> wp.Graph, or None: its capture failed
        self._seen: dict[tuple, int] = {}
        self._side_streams: dict[torch.device, torch.cuda.Stream] = {}
        self.captures = 0
        self.replays = 0
        self.eager = 0

    def clear(self) -> None:
        """Drop every graph and the counts of recent keys (the statistics above stay)."""
        self._graphs.clear()
        self._seen.clear()

    def run(self, key: tuple, queue: Callable[[], None], *, device: torch.device) -> None:
        """Queue ``queue``'s work on torch's current stream of ``device``: replayed, captured then launched, or
        run eagerly (see the module doc). ``key`` must name everything the work depends on."""
        if CAPTURE_AFTER is None or device.type != "cuda" or torch.cuda.is_current_stream_capturing():
            self.eager += 1
            queue()
            return
        graph = self._graphs.get(key, False)
        if graph is None:  # its capture failed: eager for good
            self.eager += 1
            queue()
            return
        if graph is False:
            seen = self._seen.get(key, 0) + 1
            if seen < CAPTURE_AFTER:
                if len(self._seen) >= _RECENT_KEYS:
                    self._seen.clear()
                self._seen[key] = seen
                self.eager += 1
                queue()
                return
            self._seen.pop(key, None)
            graph = self._capture(queue, device)
            self._graphs[key] = graph
            while len(self._graphs) > GRAPHS_KEPT:
                self._graphs.popitem(last=False)
            if graph is None:
                self.eager += 1
                queue()
                return
            self.captures += 1
        else:
            self._graphs.move_to_end(key)
            self.replays += 1
        _launch(graph, device)

    def _capture(self, queue: Callable[[], None], device: torch.device):
        """``queue``'s launches recorded into a Warp graph on a side stream (nothing runs), or None (warned)."""
        init_warp()
        side = self._side_streams.get(device)
        if side is None:
            side = self._side_streams[device] = torch.cuda.Stream(device=device)
        warp_stream = warp_stream_of(side)
        try:
            # Both torch's and Warp's current stream are the side stream (the caller may have selected Warp's
            # stream before: a launch on another stream would break the capture).
            with torch.cuda.stream(side), torch_stream_scope(device):
                wp.capture_begin(stream=warp_stream, force_module_load=False)
                try:
                    queue()
                finally:
                    graph = wp.capture_end(stream=warp_stream)
            return graph
        except Exception as error:  # noqa: BLE001 (any failed capture leaves the key eager)
            warnings.warn(f"capturing a repeated call's launches failed, it stays eager: {error}", RuntimeWarning)
            return None
