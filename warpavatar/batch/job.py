"""One subject's fit in a batch: the body of a Ray task, written without Ray.

An attempt always continues from the subject's checkpoint when there is one, so a task that Ray retries after
its worker died loses only the steps since the last checkpoint. A subject whose input is invalid does not
raise: its error comes back as a failed result (Ray must not retry it, and the batch goes on).
"""

from __future__ import annotations

import contextlib
import os
import signal
import time
from pathlib import Path
from typing import Callable

from warpavatar.batch.subjects import DONE_NAME, BatchSubject
from warpavatar.io.output_files import OutputBusyError, mark_output_folder, output_lock

__all__ = ["fit_subject", "INPUT_ERRORS", "TEST_KILL_MARKER"]

#: the errors that mean "this subject's input (or options) is wrong": reported, never retried
INPUT_ERRORS = (ValueError, FileNotFoundError, NotADirectoryError, PermissionError)

#: written by the test hook before it kills its worker, so only the first attempt is killed
TEST_KILL_MARKER = ".fit-many-test-killed"


def fit_subject(subject: BatchSubject, output: str | os.PathLike, *, config, device: str, preset_name: str,
                evaluate: bool, report: Callable[[str, dict], None] | None = None,
                kill_at_step: int | None = None, placement: dict | None = None) -> dict:
    """Fit ``subject`` into ``output`` (continuing from its checkpoint when there is one), evaluate it on its
    held-out folders when asked, and write the done marker.

    Args:
        subject: the subject.
        output: its output folder (created).
        config: the :class:`~warpavatar.fit.FitConfig` of every fit of the batch.
        device: torch device name of the fit (``cpu``, or ``cuda:N``: the GPU Ray gave the task, see
            :func:`~warpavatar.batch.gpus.task_cuda_device`).
        preset_name: the preset the config started from (recorded in the result).
        evaluate: measure the avatar on the subject's ``novel_view/*`` and ``novel_pose/*`` folders, at the
            fit's image scale.
        report: called as ``report(event, values)`` when the attempt starts (``"started"``, with
            ``resume_step``: the checkpoint's step, or 0).
        kill_at_step: test hook: on the first attempt only, kill this process with SIGKILL once the fit has
            done this many steps (as a lost node would), leaving the checkpoints written before.
        placement: where the task runs, recorded in the result: ``host``, and on a GPU ``gpu`` (the
            device, its name and UUID, Ray's GPU ids and the task's ``CUDA_VISIBLE_DEVICES``).

    A stop signal during the fit (SIGINT, which ``ray.cancel`` sends, SIGTERM or SIGHUP) makes it stop after
    the step under way and write its checkpoint; the result is then ``"interrupted"``, with no done marker, and
    the next attempt continues from there.

    Returns:
        The result: ``subject``, ``status`` (``"done"``, ``"failed"`` or ``"interrupted"``), ``error`` (the
        one-line message of a failed subject, else None), ``output``, ``fit_seconds`` (this attempt),
        ``resume_step``, ``steps``, ``gaussians``, ``device``, ``host`` and ``gpu`` (of ``placement``; ``gpu`` is
        None on the CPU), ``preset`` and ``eval``
        (``{"novel_view/<name>": metrics}``, empty without ``evaluate`` or held-out folders). The done marker
        holds a done result and the fit's ``config``.
    """
    output = Path(output)
    result = {"subject": subject.name, "status": "failed", "error": None, "output": str(output),
              "fit_seconds": None, "resume_step": 0, "steps": None, "gaussians": None, "device": device,
              "host": (placement or {}).get("host"), "gpu": (placement or {}).get("gpu"), "preset": preset_name,
              "eval": {}}
    try:
        with output_lock(output):  # one writer per subject: another run of the batch may be fitting it
            _fit(subject, output, config=config, device=device, evaluate=evaluate, report=report,
                 kill_at_step=kill_at_step, result=result)
    except OutputBusyError as error:  # a result, not an error to retry
        result["error"] = str(error)
    except INPUT_ERRORS as error:
        result["error"] = str(error).splitlines()[0] if str(error) else type(error).__name__
    return result


def _fit(subject: BatchSubject, output: Path, *, config, device: str, evaluate: bool, report, kill_at_step,
         result: dict) -> None:
    import torch

    from warpavatar.batch.gpus import device_kind, first_compile_turn, kernel_cache_dir
    from warpavatar.signals import stop_on_signals
    from warpavatar.evaluate import evaluate_held_out, write_json_atomic
    from warpavatar.fit import Trainer, load_training_video
    from warpavatar.fit.checkpoint import CHECKPOINT_NAME, read_checkpoint

    checkpoint = output / CHECKPOINT_NAME
    # the step only: the tensors stay in the file (the fit reads them once when it resumes)
    result["resume_step"] = int(read_checkpoint(checkpoint, mmap=True)["step"]) if checkpoint.is_file() else 0
    if report is not None:
        report("started", {"resume_step": result["resume_step"]})
    if not subject.path.is_dir():
        raise FileNotFoundError(f"{subject.path}: no such subject folder")
    mark_output_folder(output, "fit")
    video = load_training_video(subject.training_folder, config)
    start = time.time()
    # the fits starting together on a host with a cold kernel cache take turns until the first has set up and
    # taken its first step (most kernels compiled), then load what it compiled
    with contextlib.ExitStack() as compile_turn:
        compile_turn.enter_context(first_compile_turn(kernel_cache_dir(), device_kind(device)))
        trainer = Trainer(video, config, output, device=device)
        _after_first_step(trainer, compile_turn.close)
        if kill_at_step is not None and not (output / TEST_KILL_MARKER).exists():
            _kill_after(trainer, kill_at_step, output / TEST_KILL_MARKER)
        # Ray runs a task on its worker's main thread; the worker ignores SIGINT, which ray.cancel sends
        with stop_on_signals(trainer.request_stop, even_ignored=True) as stop:
            trainer.fit(resume=True, progress=False)
    result.update(fit_seconds=round(time.time() - start, 2), steps=trainer.step, gaussians=trainer.gaussians.count)
    if stop.signal_number is not None and trainer.stopped_early:
        result["status"] = "interrupted"
        return
    if evaluate and subject.subject_root is not None:
        result["eval"] = evaluate_held_out(trainer.avatar, subject.subject_root, image_scale=config.image_scale,
                                           progress=False)
        write_json_atomic(output / "eval.json", result["eval"])
    result["status"] = "done"
    write_json_atomic(output / DONE_NAME, {**result, "config": config.to_dict()})
    del trainer
    if torch.cuda.is_available():
        torch.cuda.empty_cache()  # the next fit of this worker, or a fit sharing the GPU, gets the memory back


def _after_first_step(trainer, action: Callable[[], None]) -> None:
    """Make ``trainer`` call ``action`` once, after its first training step of this session."""
    train_step = trainer.train_step
    done = []

    def train_step_then_act():
        outcome = train_step()
        if not done:
            done.append(True)
            action()
        return outcome

    trainer.train_step = train_step_then_act


def _kill_after(trainer, step: int, marker: Path) -> None:
    """Make ``trainer`` kill its own process with SIGKILL after ``step`` steps (writing ``marker`` first)."""
    train_step = trainer.train_step

    def train_step_then_kill():
        outcome = train_step()
        if trainer.step >= step:
            marker.touch()
            os.kill(os.getpid(), signal.SIGKILL)
        return outcome

    trainer.train_step = train_step_then_kill
