"""The rasterizer's intersection capacity for work that must not read the device every frame.

:func:`warpavatar.ops.rasterize_gaussians` with an ``intersection_capacity`` sizes its sort buffers to it and
reports, on the device, how many (Gaussian, tile) pairs it needed and whether any input was non-finite
(``info["status"]``). A training step and a playback frame keep that status on the device
(:meth:`IntersectionCapacity.record`) and read it now and then (:meth:`IntersectionCapacity.check`): one host
read, which raises on non-finite input and grows the capacity when a frame needed more pairs than it had (that
frame dropped pairs) or came near it. Playback reads it after every frame without waiting
(:meth:`IntersectionCapacity.poll`): a copy of the status travels to pinned host memory behind the frame's work
and is read once it has arrived, so a frame's pair count is known a frame or two later at no cost to the
device, and a capacity close to what frames need stays safe.
"""

from __future__ import annotations

import math

import torch

from warpavatar import ops

__all__ = ["IntersectionCapacity"]


class IntersectionCapacity:
    """A capacity in (Gaussian, tile) pairs and the most pairs any recorded rasterization needed.

    Args:
        device: where the statuses are kept.
        factor: the capacity is this multiple of the most pairs a frame needed (>= 1).
        minimum: the smallest capacity.
        headroom: a check grows the capacity once the most pairs needed pass this fraction of it.

    Attributes:
        value: the capacity to rasterize with, or None: exact buffers (the next frame counts its pairs).
    """

    def __init__(self, device, *, factor: float = 2.0, minimum: int = 1024, headroom: float = 0.9):
        if not factor >= 1.0:
            raise ValueError(f"capacity factor must be >= 1, got {factor}")
        self.factor, self.minimum, self.headroom = float(factor), int(minimum), float(headroom)
        self.value: int | None = None
        # [most pairs any recorded rasterization needed, OR of their input flags]
        self._status = torch.zeros(2, dtype=torch.int32, device=device)
        self._peak, self._flags = self._status[:1], self._status[1:]
        # poll(): the host copy of the status and the event after its copy (None: no copy in flight)
        self._mirror: torch.Tensor | None = None
        self._arrival: torch.cuda.Event | None = None
        self._polls_waiting = 0

    def record(self, status: torch.Tensor) -> None:
        """Keep a rasterization's ``info["status"]`` ([pair count, input flags], int32 on the device), in place and
        without a host read (capturable in a CUDA graph)."""
        torch.maximum(self._peak, status[:1], out=self._peak)
        torch.bitwise_or(self._flags, status[1:], out=self._flags)

    def check(self) -> int | None:
        """Read what was recorded (one host read): the most pairs any frame needed so far, and input flags.

        Returns:
            That peak, when it passed the capacity (frames dropped pairs), else None. The capacity is then (or when
            it was None, or the peak came near it) ``factor`` times the peak, so a peak once seen never overflows
            again.

        Raises:
            ValueError: a recorded rasterization had non-finite inputs.
        """
        peak = ops.rasterizer_status({"status": self._status})  # raises on bad inputs
        return self._grow(peak)

    def poll(self, *, max_lag: int = 3) -> int | None:
        """What :meth:`check` does, without waiting for the device while it can: reads the host copy of the
        recorded status that an earlier poll queued if it has arrived, then queues the next copy behind the work
        queued so far (on CUDA into pinned host memory; on a CPU the status is read at once).

        Args:
            max_lag: a copy still in flight at the ``max_lag``-th poll since it was queued is waited for, so what
                was recorded before a poll is read by the ``max_lag - 1``-th poll after it at the latest (1: read
                at once, :meth:`check`).

        Returns:
            As :meth:`check`, for the status the copy read (None too when none arrived).

        Raises:
            ValueError: a recorded rasterization had non-finite inputs.
        """
        if self._status.device.type != "cuda" or max_lag <= 1:
            return self.check()
        peak = None
        if self._arrival is not None:
            self._polls_waiting += 1
            if self._polls_waiting >= max_lag - 1 or self._arrival.query():
                self._arrival.synchronize()  # (a completed event returns at once)
                peak = ops.rasterizer_status({"status": self._mirror})  # a host tensor: no device read
                self._arrival = None
        if self._arrival is None:
            if self._mirror is None:
                self._mirror = torch.empty(2, dtype=torch.int32, pin_memory=True)
            self._mirror.copy_(self._status, non_blocking=True)
            self._arrival = torch.cuda.Event()
            self._arrival.record()
            self._polls_waiting = 0
        return None if peak is None else self._grow(peak)

    def _grow(self, peak: int) -> int | None:
        """Grow the capacity for a ``peak`` of pairs; the peak when it passed the capacity, else None."""
        overflow = peak if self.value is not None and peak > self.value else None
        if self.value is None or peak > self.headroom * self.value:
            self.value = max(self.minimum, math.ceil(self.factor * peak))
        return overflow
