"""The fit's training log, ``train_log.jsonl`` in its output folder: one JSON record a line (the warm-up's, each
logging step's loss terms and statistics, notes such as a grown rasterizer capacity)."""

from __future__ import annotations

import json
import os
from pathlib import Path

from warpavatar.extensions import LossTerm, StepContext
from warpavatar.io.output_files import append_text
from warpavatar.metrics import psnr

__all__ = ["TRAINING_LOG_NAME", "TrainingLog", "step_log_record"]

TRAINING_LOG_NAME = "train_log.jsonl"
"""The training log's file name in a fit's output folder."""


class TrainingLog:
    """Appends records to one training log file.

    Args:
        path: the log file (made on the first record).
    """

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)

    def clear(self) -> None:
        """Remove the log an earlier fit left (a fit that starts over)."""
        self.path.unlink(missing_ok=True)

    def write(self, record: dict) -> None:
        """Append ``record`` as one line of JSON.

        Raises:
            DiskFullError: the disk filled up (one line naming the log).
        """
        append_text(self.path, json.dumps(record) + "\n")


def step_log_record(step: StepContext, terms: dict[str, LossTerm], *, extensions, stages=(), gaussian_count: int,
                    step_number: int, seconds: float) -> dict:
    """The record of a logging step; reading it from the device is the only host read of a step.

    Args:
        step: the finished step (``image`` [H,W,3] and ``target`` [H,W,3]).
        terms: the step's loss terms (detached), ``loss`` among them.
        extensions: the enabled extensions, whose ``log_values()`` follow the terms.
        stages: further parts with ``log_values()`` (the step graph, the skinning stage), after the PSNR.
        gaussian_count: the number of Gaussians after the step.
        step_number: the number of steps done.
        seconds: time since the fit (or its resume) began [s], rounded to 0.01 s.

    Returns:
        Each term's value by name, the extensions' values, ``psnr`` [dB], ``gaussians``, the stages' values,
        ``step`` and ``seconds``, in this order.
    """
    record = {name: float(term.value.detach()) for name, term in terms.items()}
    for extension in extensions:
        record.update(extension.log_values())
    record.update(psnr=psnr(step.image.detach(), step.target), gaussians=gaussian_count)
    for stage in stages:
        record.update(stage.log_values())
    return {**record, "step": step_number, "seconds": round(seconds, 2)}
