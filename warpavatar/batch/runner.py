"""The Ray side of a batch: one task per subject with the resources a fit needs, bounded retries that resume
from the subject's checkpoint, a progress line per subject and an overall bar.

Ray is imported here only, when a batch runs; without it :func:`import_ray` says how to install it.
"""

from __future__ import annotations

import os
import socket
import time
from pathlib import Path
from typing import Callable

from warpavatar.batch.job import fit_subject
from warpavatar.batch.report import one_line_result
from warpavatar.batch.subjects import DONE_NAME, BatchSubject, finished_result

__all__ = ["run_batch", "connect_ray", "cluster_gpu_count", "import_ray", "task_placement", "RAY_INSTALL_HINT",
           "INFRASTRUCTURE_ERRORS", "STOP_GRACE_SECONDS"]

RAY_INSTALL_HINT = ('warpavatar-fit-many needs Ray, an optional dependency: pip install -e ".[cluster]" '
                    '(or pip install "ray>=2.9")')


def _infrastructure_errors() -> tuple[type[BaseException], ...]:
    import torch

    # a disk or network file system that failed, a GPU shared with other fits that ran out of memory; a dead
    # worker (killed, lost node) is retried by Ray whatever the exception list says
    return (OSError, torch.cuda.OutOfMemoryError)


#: exceptions of a task that Ray retries (the subject's own input errors are results, never raised)
INFRASTRUCTURE_ERRORS = _infrastructure_errors()

STOP_GRACE_SECONDS = 300.0
"""How long an interrupted batch waits for its running fits to finish their step and write their checkpoints
before it kills them."""


def import_ray():
    """The ``ray`` module.

    Raises:
        ModuleNotFoundError: Ray is not installed (the message says how to install it).
    """
    try:
        import ray
    except ImportError as error:
        raise ModuleNotFoundError(RAY_INSTALL_HINT) from error
    return ray


def connect_ray(address: str | None) -> bool:
    """Join the Ray cluster at ``address`` (``auto`` or ``HOST:PORT``), or start a local Ray instance on this
    machine when ``address`` is None; keep a connection this process already has. Returns whether this call
    connected (the caller then shuts Ray down when done)."""
    import logging

    ray = import_ray()
    if ray.is_initialized():
        return False
    options = dict(include_dashboard=False, log_to_driver=False, logging_level=logging.WARNING)
    if address is None:
        ray.init(**options)
    else:
        ray.init(address=address, **options)
    return True


def cluster_gpu_count() -> float:
    """The GPUs of the connected Ray cluster (0 where it has none)."""
    return float(import_ray().cluster_resources().get("GPU", 0.0))


def task_placement(device: str, gpu_ids, *, environ=os.environ) -> dict:
    """Where this task's fit runs: ``{"device": torch device, "host": ..., "gpu": ...}``.

    On CUDA the device is the GPU Ray gave the task (:func:`~warpavatar.batch.gpus.task_cuda_device` of
    ``gpu_ids``, ``ray.get_gpu_ids()``), made torch's and Warp's current device; ``gpu`` describes it (name,
    UUID, Ray's ids, ``CUDA_VISIBLE_DEVICES``). On the CPU ``gpu`` is None."""
    placement = {"device": device, "host": socket.gethostname(), "gpu": None}
    if device != "cuda":
        return placement
    import torch

    from warpavatar.batch.gpus import describe_cuda_device, task_cuda_device, use_cuda_device

    ids = [str(gpu_id) for gpu_id in gpu_ids]
    visible = environ.get("CUDA_VISIBLE_DEVICES")
    placement["device"] = task_cuda_device(ids, visible_devices=visible, device_count=torch.cuda.device_count())
    use_cuda_device(placement["device"])
    placement["gpu"] = {**describe_cuda_device(placement["device"]), "ray_gpu_ids": ids,
                        "cuda_visible_devices": visible}
    return placement


def _subject_task(events, subject: BatchSubject, output: str, options: dict, kill_at_step: int | None) -> dict:
    """The Ray task of one subject: :func:`~warpavatar.batch.job.fit_subject` on the device Ray gave it
    (:func:`task_placement`), reporting its start."""
    placement = task_placement(options["device"], import_ray().get_gpu_ids())
    where = {"host": placement["host"], "gpu_uuid": (placement["gpu"] or {}).get("uuid")}

    def report(event: str, values: dict) -> None:
        events.put((subject.name, event, {**values, **where}))

    return fit_subject(subject, output, report=report, kill_at_step=kill_at_step,
                       placement=placement, **{**options, "device": placement["device"]})


def _task_error(error: BaseException) -> str:
    """One line for a task that failed after its retries: the exception it raised, or why its worker died."""
    cause = getattr(error, "cause", None)
    if isinstance(cause, BaseException):
        error = cause
    lines = [line.strip() for line in str(error).splitlines() if line.strip()]
    text = lines[-1] if lines else ""
    return f"{type(error).__name__}: {text}" if text else type(error).__name__


def _earlier_results(subjects: list[BatchSubject], out_root: Path, *, config, force: bool):
    """The results of subjects an earlier run finished (``"skipped"``; ``"failed"`` where it used other options)
    and the subjects to fit; with ``force`` every subject is fitted, its checkpoint and done marker removed."""
    from warpavatar.fit.checkpoint import CHECKPOINT_NAME
    from warpavatar.fit.config import FitConfig, changed_options

    results, to_fit = {}, []
    for subject in subjects:
        output = subject.output(out_root)
        earlier = None if force else finished_result(output)
        if earlier is None:
            if force:
                for name in (DONE_NAME, CHECKPOINT_NAME):
                    (output / name).unlink(missing_ok=True)
            to_fit.append(subject)
            continue
        changed = [name for name, _, _ in changed_options(FitConfig.from_dict(earlier["config"]), config)]
        result = {key: value for key, value in earlier.items() if key != "config"}
        result.update(status="failed" if changed else "skipped", attempts=0, wall_seconds=0.0,
                      error=f"{output}: finished by an earlier run with other options ({', '.join(changed)}); "
                            "--force fits it again with these" if changed else None)
        results[subject.name] = result
    return results, to_fit


def run_batch(subjects: list[BatchSubject], out_root: str | os.PathLike, *, config, device: str, preset_name: str,
              gpus_per_fit: float, cpus_per_fit: float, max_retries: int = 3, evaluate: bool = False,
              force: bool = False, progress: bool = True, test_kill: dict[str, int] | None = None,
              write: Callable[[str], None] | None = None, stop_requested: Callable[[], bool] | None = None,
              kernel_cache: str | os.PathLike | None = None) -> list[dict]:
    """Fit every subject in its own Ray task on the connected cluster (see :func:`connect_ray`).

    Subjects finished by an earlier run (their done marker) are skipped unless ``force``, which fits them again
    from the start; one finished with other options fails (with the options that differ) rather than be
    skipped. Each task asks for ``gpus_per_fit`` GPUs (a fraction shares one) and ``cpus_per_fit`` CPUs;
    a task whose worker dies, or that raises one of :data:`INFRASTRUCTURE_ERRORS`, runs again up to
    ``max_retries`` times, continuing from the subject's checkpoint. A subject with invalid input fails alone.

    Args:
        subjects: the subjects (:func:`~warpavatar.batch.subjects.read_subjects`).
        out_root: each subject's outputs go to ``out_root/<name>/``.
        config: the :class:`~warpavatar.fit.FitConfig` of every fit.
        device: the fits' torch device (``cuda``: the GPU Ray assigns).
        preset_name: the preset ``config`` started from (recorded).
        gpus_per_fit: GPUs a fit asks Ray for (0 on CPU; 0.5: two fits share a GPU).
        cpus_per_fit: CPUs a fit asks Ray for.
        max_retries: how many times a task is run again after its worker died or an infrastructure error.
        evaluate: measure each avatar on its subject's held-out folders.
        force: fit finished subjects again (their checkpoint and done marker are removed first).
        progress: show the overall progress bar.
        test_kill: test hook: ``{subject name: step}``, the first attempt of that subject's task kills its
            worker with SIGKILL after that step.
        write: where the progress lines go (default: printed above the bar).
        stop_requested: asked while the batch runs; true stops it (see above).
        kernel_cache: Warp's kernel cache directory for every fit (``WARP_CACHE_PATH`` in each worker's
            environment); None: each worker's own ``WARP_CACHE_PATH`` or Warp's per-user cache directory. The
            fits of a host share it and compile each kernel once (:func:`~warpavatar.batch.gpus.first_compile_turn`).

    Returns:
        One result per subject, in the order given: :func:`~warpavatar.batch.job.fit_subject`'s, with
        ``status`` ``"skipped"`` for a subject an earlier run finished with the same options, and ``attempts``
        (how many times its task started) and ``wall_seconds`` (from its first start to its end, as the driver
        saw them); ``"interrupted"`` for a subject stopped before its end.

    Stopping: once ``stop_requested()`` is true (it is asked twice a second), every running fit is asked to stop
    after its step under way and write its checkpoint, and queued ones are cancelled; the batch waits for them
    (at most :data:`STOP_GRACE_SECONDS`, then kills them) and returns, those subjects ``"interrupted"``. A
    KeyboardInterrupt (Ctrl-C where no handler records it) stops them the same way and is raised again; a second
    one kills them at once.
    """
    import tqdm

    ray = import_ray()
    from ray.util.queue import Queue

    out_root = Path(out_root)
    out_root.mkdir(parents=True, exist_ok=True)
    bar = tqdm.tqdm(total=len(subjects), disable=not progress, desc="subjects", unit="fit")
    write = write or bar.write
    results, to_fit = _earlier_results(subjects, out_root, config=config, force=force)
    for result in results.values():
        write(one_line_result(result))
        bar.update(1)
    if not to_fit:
        bar.close()
        return [results[subject.name] for subject in subjects]

    events = Queue(actor_options={"num_cpus": 0})
    # resources given to ray.remote itself (not .options): a GPU task then gets Ray's default max_calls=1, a fresh
    # worker process per fit, whose GPU memory is freed when it ends
    environment = {"env_vars": {"WARP_CACHE_PATH": str(Path(kernel_cache).absolute())}} if kernel_cache else None
    task = ray.remote(num_gpus=gpus_per_fit, num_cpus=cpus_per_fit, max_retries=max_retries,
                      retry_exceptions=list(INFRASTRUCTURE_ERRORS), runtime_env=environment)(_subject_task)
    options = dict(config=config, device=device, preset_name=preset_name, evaluate=evaluate)
    pending = {task.remote(events, subject, str(subject.output(out_root)), options,
                           (test_kill or {}).get(subject.name)): subject for subject in to_fit}
    attempts = {subject.name: 0 for subject in to_fit}
    first_start: dict[str, float] = {}

    def drain_events() -> None:
        count = events.qsize()
        for name, event, values in events.get_nowait_batch(count) if count else []:
            if event == "started":
                attempts[name] += 1
                first_start.setdefault(name, time.time())
                again = f", attempt {attempts[name]}" if attempts[name] > 1 else ""
                resume = f", resuming from step {values['resume_step']}" if values["resume_step"] else ""
                gpu = f" ({values['gpu_uuid']})" if values.get("gpu_uuid") else ""
                write(f"{name}: started on {values['host']}{gpu}{again}{resume}")

    def collect(ready) -> None:
        for reference in ready:
            subject = pending.pop(reference)
            try:
                result = ray.get(reference)
            except ray.exceptions.TaskCancelledError:
                result = {"subject": subject.name, "status": "interrupted", "error": None, "steps": None,
                          "output": str(subject.output(out_root)), "eval": {}}
            except ray.exceptions.RayError as error:
                result = {"subject": subject.name, "status": "failed", "error": _task_error(error),
                          "output": str(subject.output(out_root)), "eval": {}}
            start = first_start.get(subject.name, time.time())
            result.update(attempts=attempts[subject.name], wall_seconds=round(time.time() - start, 2))
            results[subject.name] = result
            write(one_line_result(result))
            bar.update(1)

    def stop_tasks() -> None:
        # ray.cancel without force delivers SIGINT to each running task: its fit (fit_subject) stops after the
        # step under way and writes its checkpoint; a queued task never starts
        write(f"stopping {len(pending)} fits after their step under way (each writes its checkpoint)")
        for reference in pending:
            ray.cancel(reference, force=False)
        deadline = time.time() + STOP_GRACE_SECONDS
        while pending and time.time() < deadline:
            ready, _ = ray.wait(list(pending), num_returns=len(pending), timeout=0.5)
            drain_events()
            collect(ready)

    stopping = False
    try:
        while pending and not (stop_requested is not None and stop_requested()):
            ready, _ = ray.wait(list(pending), num_returns=1, timeout=0.5)
            drain_events()
            collect(ready)
        if pending:
            stopping = True
            stop_tasks()
    except KeyboardInterrupt:
        if not stopping:  # while the fits stop, a (second) interruption kills them instead: finally below
            stopping = True
            stop_tasks()
        raise
    finally:
        bar.close()
        for reference in pending:
            ray.cancel(reference, force=True)
        ray.kill(events.actor)
    for subject in to_fit:  # killed after STOP_GRACE_SECONDS: their last checkpoint stays
        results.setdefault(subject.name, {"subject": subject.name, "status": "interrupted", "error": None,
                                          "steps": None, "output": str(subject.output(out_root)), "eval": {},
                                          "attempts": attempts[subject.name], "wall_seconds": None})
    return [results[subject.name] for subject in subjects]
