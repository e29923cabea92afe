"""Wall seconds of a fit's phases (loading, initialization, warm-up, training steps, each output), measured at the
phase boundaries only: one clock read at each, and on CUDA one device synchronization at each, so that a phase's
queued kernels count in it and not in the next. Inside the training loop only the rare events are phases of
their own (densification rounds, checkpoints), each of which reads the device anyway."""

from __future__ import annotations

import contextlib
import time

import torch

__all__ = ["PhaseClock"]


class PhaseClock:
    """Adds up the wall seconds spent in named phases, in the order they first ran.

    A phase may run inside another (a checkpoint among the training steps): the outer one's clock stops while
    the inner one runs, so the phases never count the same second twice and their sum is the wall time they
    cover.

    Args:
        device: the device whose queued work a phase waits for at its start and end (CUDA only; elsewhere the
            work is done when the call returns).

    Attributes:
        seconds: phase name -> wall seconds [s], summed over every time the phase ran in this process.
    """

    def __init__(self, device="cpu"):
        self.device = torch.device(device)
        self.seconds: dict[str, float] = {}
        self._running: list[list] = []  # [name, start] of the phases under way, innermost last

    def _now(self) -> float:
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
        return time.perf_counter()

    def _add(self, name: str, seconds: float) -> None:
        self.seconds[name] = self.seconds.get(name, 0.0) + seconds

    @contextlib.contextmanager
    def phase(self, name: str):
        """Time the ``with`` block as phase ``name`` (its seconds are added to those it already has)."""
        now = self._now() if self._running else time.perf_counter()  # the outer phase's queued work is its own
        if self._running:
            outer = self._running[-1]
            self._add(outer[0], now - outer[1])
        entry = [name, now]
        self._running.append(entry)
        try:
            yield
        finally:
            end = self._now()
            self._running.pop()
            self._add(name, end - entry[1])
            if self._running:
                self._running[-1][1] = end  # the outer phase's clock runs again

    def rounded(self, digits: int = 3) -> dict[str, float]:
        """The phases' seconds rounded to ``digits`` decimals, plus ``total`` (their sum), for logs and reports."""
        values = {name: round(value, digits) for name, value in self.seconds.items()}
        values["total"] = round(sum(self.seconds.values()), digits)
        return values
