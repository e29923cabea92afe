"""A few int32 status values read by the host as soon as the device has written them, not when its stream is idle.

A speculative rasterizer pass (:mod:`warpavatar._src.splat`) needs two numbers from the device before it can
return: how many (Gaussian, tile) pairs the image needs and the non-finite-input flags. Both are known once the
projection, the depth sort and the prefix sum have run, a small share of the pass; the compositing, most of the GPU
time, comes after. Reading them with ``tensor.tolist()`` waits for the whole stream, so the host's work after the
read (the sorted ids' copy, autograd's bookkeeping, the caller's next steps) cannot overlap the compositing. A
:class:`StatusMailbox` is a small block of pinned host memory that the pass fills with an asynchronous copy queued
right after the prefix sum (inside a captured graph too: a copy into pinned memory is an ordinary graph node); the
host marks the block empty before it queues the pass (:meth:`StatusMailbox.arm`), and :meth:`StatusMailbox.read`
returns as soon as the copy has landed, while the stream goes on.

Reading waits by polling the pinned memory for at most :data:`POLL_SECONDS`, then blocks on the stream as
``tolist`` would (a GPU with a long queue of earlier work, or an error: the stream's synchronization raises it).
Mailboxes are kept per thread, device and stream: a pass's copy and its reader always pair up, and the block's
address is fixed, so a graph that holds the copy can be replayed.

On CPU the kernels run synchronously: the copy is made at once and reading returns it.
"""

from __future__ import annotations

import ctypes
import threading
import time

import torch

from warpavatar._src.warp_utils import current_stream_handle, native_entry, warp_context

__all__ = ["POLL_SECONDS", "StatusMailbox", "status_mailbox"]

POLL_SECONDS = 2e-3
"""How long :meth:`StatusMailbox.read` polls the pinned memory before it blocks on the stream instead [s]."""

_EMPTY = -1  # what an armed mailbox holds; the values posted are counts and flags, never negative


class StatusMailbox:
    """``slots`` int32 values in pinned host memory that the device writes and the host polls (see the module
    doc). Made by :func:`status_mailbox`."""

    __slots__ = ("slots", "device", "address", "_host", "_values")

    def __init__(self, slots: int, device: torch.device):
        self.slots = slots
        self.device = device
        pinned = device.type == "cuda"
        self._host = torch.full((slots,), _EMPTY, dtype=torch.int32, pin_memory=pinned)
        self._values = self._host.numpy()
        self.address = self._host.data_ptr()
        """The pinned block's address (fixed for the mailbox's life: a key of the graphs that post to it)."""

    def arm(self) -> None:
        """Mark the mailbox empty; call before queueing the work that posts to it."""
        self._values.fill(_EMPTY)

    def post(self, source: torch.Tensor) -> None:
        """Queue the copy of ``source`` (``slots`` contiguous int32 on the mailbox's device, values >= 0 once
        written) into the mailbox on torch's current stream (during a CUDA graph capture, into the graph)."""
        if source.dtype != torch.int32 or source.numel() != self.slots or not source.is_contiguous():
            raise ValueError(f"a status mailbox of {self.slots} int32 takes {self.slots} contiguous int32, got "
                             f"{source.dtype} {list(source.shape)}")
        if self.device.type != "cuda":
            self._values[:] = source.numpy()
            return
        copy = native_entry("wp_memcpy_d2h")  # (context, dest, src, bytes, stream), what wp.copy ends in
        if copy is None:
            self._host.copy_(source, non_blocking=True)
            return
        if not copy(warp_context(self.device), ctypes.c_void_p(self.address), ctypes.c_void_p(source.data_ptr()),
                    4 * self.slots, ctypes.c_void_p(current_stream_handle(self.device))):
            raise RuntimeError("queueing the status copy to pinned host memory failed")

    def read(self) -> list[int]:
        """The values posted since :meth:`arm`, waiting for them as described in the module doc.

        Raises:
            RuntimeError: the stream finished without the copy having landed (nothing posted since ``arm``).
        """
        values = self._values
        if values.min() >= 0:
            return values.tolist()
        deadline = time.perf_counter() + POLL_SECONDS
        while time.perf_counter() < deadline:
            for _ in range(32):
                if values.min() >= 0:
                    return values.tolist()
        if self.device.type == "cuda":
            torch.cuda.current_stream(self.device).synchronize()  # raises the stream's errors, if any
        if values.min() < 0:
            raise RuntimeError("the device's status copy never arrived (nothing was posted to the mailbox)")
        return values.tolist()


_LOCAL = threading.local()


def status_mailbox(device: torch.device, slots: int = 2) -> StatusMailbox:
    """This thread's mailbox of ``slots`` values for torch's current stream of ``device`` (made on first use)."""
    mailboxes = getattr(_LOCAL, "mailboxes", None)
    if mailboxes is None:
        mailboxes = _LOCAL.mailboxes = {}
    stream = current_stream_handle(device) if device.type == "cuda" else 0
    key = (device, stream, slots)
    mailbox = mailboxes.get(key)
    if mailbox is None:
        mailbox = mailboxes[key] = StatusMailbox(slots, device)
    return mailbox
