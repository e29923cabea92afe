"""The rasterizer's intersection capacity for work that must not read the device every frame.

:func:`warpavatar.ops.rasterize_gaussians` with an ``intersection_capacity`` sizes its sort buffers to it and
reports, on the device, how many (Gaussian, tile) pairs it needed and whether any input was non-finite
(``info["status"]``). A training step and a playback frame keep that status on the device
(:meth:`IntersectionCapacity.record`) and read it now and then (:meth:`IntersectionCapacity.check`): one host
read, which raises on non-finite input and grows the capacity when a frame needed more pairs than it had (that
frame dropped pairs) or came near it.
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
        self._peak = torch.zeros(1, dtype=torch.int32, device=device)
        self._flags = torch.zeros(1, dtype=torch.int32, device=device)

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
        peak = ops.rasterizer_status({"status": torch.cat([self._peak, self._flags])})  # raises on bad inputs
        overflow = peak if self.value is not None and peak > self.value else None
        if self.value is None or peak > self.headroom * self.value:
            self.value = max(self.minimum, math.ceil(self.factor * peak))
        return overflow
