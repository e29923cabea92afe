"""Capturing torch and Warp work together into one CUDA graph, and replaying it.

Warp's kernels run on torch's current stream (:func:`~warpavatar._src.warp_utils.torch_stream_scope`), so a
torch capture (``torch.cuda.graph``) records them too once Warp is told that an external capture is active
(``wp.capture_begin(external=True)``, as Warp's PyTorch interoperability guide shows). The captured function
must not read anything from the device and must not allocate with Warp's allocator (every buffer here is a
torch tensor, which the capture takes from its private memory pool); it is run a few times on the capture
stream first, so that Warp modules are loaded and torch's allocator and Warp's sort scratch space are warm.
"""

from __future__ import annotations

import warnings
from typing import Any, Callable

import torch
import warp as wp

from warpavatar._src.warp_utils import init_warp, warp_device, warp_stream_of

__all__ = ["CAPTURE_MODE", "cuda_graphs_available", "capture_cuda_graph", "capture_or_fall_back", "resolve_cuda_graph"]

CAPTURE_MODE = "thread_local"
"""The CUDA stream-capture mode of both sides (torch's ``capture_error_mode``: ``global``, ``thread_local`` or
``relaxed``; Warp's matching :class:`warp.CaptureMode`)."""


def cuda_graphs_available(device) -> bool:
    """Whether ``device`` is a CUDA device (the only kind whose work can be captured)."""
    return torch.device(device).type == "cuda" and torch.cuda.is_available()


def resolve_cuda_graph(mode: str, device) -> bool:
    """The ``--cuda-graph`` setting (``auto``, ``on``, ``off``) as a yes/no for ``device``.

    Raises:
        ValueError: an unknown mode, or ``on`` on a device without CUDA graphs.
    """
    if mode not in ("auto", "on", "off"):
        raise ValueError(f"cuda_graph must be auto, on or off, got {mode!r}")
    available = cuda_graphs_available(device)
    if mode == "on" and not available:
        raise ValueError(f"--cuda-graph on needs a CUDA device, the device is {torch.device(device)}")
    return available and mode != "off"


def capture_cuda_graph(function: Callable[[], Any], *, device, warmup: int = 2, stream=None
                       ) -> tuple[torch.cuda.CUDAGraph, Any]:
    """Run ``function`` ``warmup`` times on a side stream, then capture one call into a CUDA graph.

    Args:
        function: the work; takes no arguments, reads its inputs from tensors the caller refills before each
            replay, and returns its outputs (tensors that each replay overwrites in place).
        device: the CUDA device.
        warmup: eager calls before the capture (they load Warp modules and warm the allocator; 0 when the
            caller already ran ``function``'s work eagerly on ``stream``, e.g. a training step with side effects).
        stream: the side stream (a ``torch.cuda.Stream`` of ``device``; default a new one).

    Returns:
        ``(graph, outputs)``: ``graph.replay()`` reruns the work, leaving its results in ``outputs``.
    """
    init_warp()
    device = torch.device(device)
    name = warp_device(device)
    stream = torch.cuda.Stream(device=device) if stream is None else stream
    stream.wait_stream(torch.cuda.current_stream(device))
    with torch.cuda.stream(stream):
        for _ in range(warmup):
            function()
    torch.cuda.current_stream(device).wait_stream(stream)
    graph = torch.cuda.CUDAGraph()
    warp_stream = warp_stream_of(stream)
    # one capture mode on both sides (Warp must be told the mode of the capture torch opened)
    with wp.ScopedDevice(name), wp.ScopedStream(warp_stream, sync_enter=False), \
            torch.cuda.graph(graph, stream=stream, capture_error_mode=CAPTURE_MODE):
        wp.capture_begin(stream=warp_stream, force_module_load=False, external=True,
                         capture_mode=getattr(wp.CaptureMode, CAPTURE_MODE.upper()))
        try:
            outputs = function()
        finally:
            wp.capture_end(stream=warp_stream)
    return graph, outputs


def capture_or_fall_back(function: Callable[[], Any], *, mode: str, what: str, device, **options
                         ) -> tuple[torch.cuda.CUDAGraph, Any] | None:
    """:func:`capture_cuda_graph`, or None where the capture fails under ``mode`` ``auto`` (with a warning
    naming ``what`` goes on eagerly); under ``on`` the failure raises.

    Any exception counts (torch 2.11 raises ``AcceleratorError`` for a failed capture).
    """
    try:
        return capture_cuda_graph(function, device=device, **options)
    except Exception as error:  # noqa: BLE001 (see above)
        if mode == "on":
            raise
        warnings.warn(f"CUDA graph capture failed, {what} goes on eagerly: {error}", RuntimeWarning)
        return None
