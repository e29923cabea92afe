"""Wall seconds of a fit's phases (loading, initialization, warm-up, training steps, each output), measured at the
phase boundaries only: one clock read at each, and on CUDA one device synchronization at each end, so that a
phase's queued kernels count in it and not in the next. Nothing is read inside the training loop."""

from __future__ import annotations

import contextlib
import time

import torch

__all__ = ["PhaseClock"]


class PhaseClock:
    """Adds up the wall seconds spent in named phases, in the order they first ran.

    Args:
        device: the device whose queued work a phase waits for at its end (CUDA only; elsewhere the work is
            done when the call returns).

    Attributes:
        seconds: phase name -> wall seconds [s], summed over every time the phase ran in this process.
    """

    def __init__(self, device="cpu"):
        self.device = torch.device(device)
        self.seconds: dict[str, float] = {}

    @contextlib.contextmanager
    def phase(self, name: str):
        """Time the ``with`` block as phase ``name`` (its seconds are added to those it already has)."""
        start = time.perf_counter()
        try:
            yield
        finally:
            if self.device.type == "cuda":
                torch.cuda.synchronize(self.device)
            self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - start

    def rounded(self, digits: int = 3) -> dict[str, float]:
        """The phases' seconds rounded to ``digits`` decimals, plus ``total`` (their sum), for logs and reports."""
        values = {name: round(value, digits) for name, value in self.seconds.items()}
        values["total"] = round(sum(self.seconds.values()), digits)
        return values
