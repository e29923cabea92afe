"""Timing and table helpers shared by the kernel micro-benchmarks (tools/bench_*.py).

Method (as gsplat's profiling scripts): warm up, synchronize, time each repetition with CUDA events on
CUDA (``time.perf_counter`` on CPU), report the median, and read peak memory from torch's allocator.
"""

from __future__ import annotations

import statistics
import time
from typing import Callable

import torch

__all__ = ["time_function", "peak_memory_scope", "markdown_table", "interleaved_rounds", "value_range"]


def time_function(fn: Callable[[], object], *, device: str, warmup: int = 5, repeats: int = 20) -> float:
    """Median wall time of ``fn()`` in milliseconds.

    Args:
        fn: the work to time; called ``warmup + repeats`` times.
        device: ``"cpu"`` or ``"cuda:N"``; on CUDA each call is bracketed by CUDA events on the current stream.
        warmup: untimed calls first (kernel compilation, allocator warm-up).
        repeats: timed calls; the median is returned.
    """
    for _ in range(warmup):
        fn()
    times = []
    if device.startswith("cuda"):
        torch.cuda.synchronize(device)
        for _ in range(repeats):
            start = torch.cuda.Event(enable_timing=True)
            end = torch.cuda.Event(enable_timing=True)
            start.record()
            fn()
            end.record()
            end.synchronize()
            times.append(start.elapsed_time(end))
    else:
        for _ in range(repeats):
            t0 = time.perf_counter()
            fn()
            times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times)


class peak_memory_scope:
    """Context manager measuring the peak CUDA memory allocated by torch inside it, in MiB.

    ``scope.peak_mib`` is the peak above what was allocated on entry (None on CPU).
    Memory that Warp allocates itself through its own allocator is not seen: bridges in warpavatar allocate
    outputs and scratch buffers with torch, so this covers them.
    """

    def __init__(self, device: str):
        self.device = device
        self.peak_mib = None

    def __enter__(self):
        if self.device.startswith("cuda"):
            torch.cuda.synchronize(self.device)
            torch.cuda.reset_peak_memory_stats(self.device)
            self._base = torch.cuda.memory_allocated(self.device)
        return self

    def __exit__(self, *exc):
        if self.device.startswith("cuda"):
            torch.cuda.synchronize(self.device)
            self.peak_mib = (torch.cuda.max_memory_allocated(self.device) - self._base) / 2**20
        return False


def markdown_table(rows: list[dict]) -> str:
    """Format a list of dicts (same keys, in order) as a GitHub markdown table."""
    if not rows:
        return "(no rows)"
    keys = list(rows[0].keys())
    for row in rows[1:]:
        keys += [k for k in row if k not in keys]

    def cell(value):
        if value is None:
            return "-"
        if isinstance(value, float):
            return f"{value:.3f}" if abs(value) < 100 else f"{value:.1f}"
        return str(value)

    lines = ["| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
    lines += ["| " + " | ".join(cell(row.get(k)) for k in keys) + " |" for row in rows]
    return "\n".join(lines)


def interleaved_rounds(measures: dict[str, Callable[[], object] | None], rounds: int) -> dict[str, list]:
    """Call each measurement ``rounds`` times, the order reversed every other round (so that a machine's drift, a
    clock that settles or a neighbour's load, falls on both sides), and return each one's results in round order.

    Args:
        measures: name -> a function returning one measurement (None: skipped, gets an empty list).
        rounds: how many times each runs (>= 1).
    """
    if rounds < 1:
        raise ValueError(f"rounds must be >= 1, got {rounds}")
    names = [name for name, measure in measures.items() if measure is not None]
    results: dict[str, list] = {name: [] for name in measures}
    for index in range(rounds):
        for name in (names if index % 2 == 0 else names[::-1]):
            results[name].append(measures[name]())
    return results


def value_range(values: list, digits: int = 3):
    """One value (or several equal ones) as itself; several as the string ``"low-high"`` with ``digits`` decimals
    (a table cell); none, or any None among them, as None."""
    if not values or any(value is None for value in values):
        return None
    low, high = min(values), max(values)
    if len(values) == 1 or low == high:
        return values[0]
    return f"{low:.{digits}f}-{high:.{digits}f}"

