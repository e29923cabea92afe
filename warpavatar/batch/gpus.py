"""Which GPU a batch's fit runs on, and the kernel cache its host shares; written without Ray, so it is tested
without a cluster or a GPU.

Ray gives a task of ``num_gpus`` its GPUs by their ids (``ray.get_gpu_ids()``) and, unless told not to, narrows
the worker's ``CUDA_VISIBLE_DEVICES`` to them before the task runs, so the task's GPU is then ``cuda:0`` for
torch and for Warp alike. :func:`task_cuda_device` turns those facts into the torch device of the fit and refuses
a worker whose CUDA saw other GPUs (it was initialized before Ray narrowed the visibility), rather than fit on a
GPU another task was given. :func:`use_cuda_device` makes that device the current one of torch and of Warp, and
:func:`describe_cuda_device` names it by the UUID ``nvidia-smi -L`` prints, checking that torch and Warp see the
same GPU.

Every fit on a host compiles its Warp kernels into one kernel cache directory (Warp's per-user one, or the one
``warpavatar-fit-many --kernel-cache`` or ``WARP_CACHE_PATH`` names). While the cache has no record that the
kernels of this code were compiled there for this device, the fits that start at the same time take turns
(:func:`first_compile_turn`): the first compiles, the others then load what it wrote.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import os
from pathlib import Path
from typing import Iterator, Sequence

__all__ = ["task_cuda_device", "use_cuda_device", "describe_cuda_device", "device_kind", "kernel_cache_dir",
           "first_compile_turn", "compiled_marker_name", "KERNEL_CACHE_VARIABLE"]

#: the environment variable Warp reads its kernel cache directory from
KERNEL_CACHE_VARIABLE = "WARP_CACHE_PATH"


def _visible_list(visible_devices: str | None) -> list[str] | None:
    """``CUDA_VISIBLE_DEVICES`` as a list of ids (None where it is unset)."""
    if visible_devices is None:
        return None
    return [entry.strip() for entry in visible_devices.split(",") if entry.strip()]


def task_cuda_device(gpu_ids: Sequence[int | str], *, visible_devices: str | None, device_count: int) -> str:
    """The torch device (``"cuda:N"``) of the GPU Ray gave a task.

    Args:
        gpu_ids: ``ray.get_gpu_ids()`` inside the task: the ids of its GPUs (integers, or the entries of the
            node's ``CUDA_VISIBLE_DEVICES``, which may be UUIDs). With a fraction of a GPU, the GPU shared.
        visible_devices: the task's ``CUDA_VISIBLE_DEVICES`` (None where unset).
        device_count: how many GPUs CUDA shows this process (``torch.cuda.device_count()``).

    Returns:
        ``"cuda:0"`` when CUDA shows the task only its GPUs (Ray narrowed ``CUDA_VISIBLE_DEVICES`` to them);
        otherwise (Ray left the visibility alone, as with ``RAY_EXPERIMENTAL_NOSET_CUDA_VISIBLE_DEVICES``) the
        position of the task's first GPU among the visible ones.

    Raises:
        RuntimeError: the task has no GPU, CUDA shows none, or the task's GPU is not among those CUDA shows
            (the worker's CUDA was initialized before Ray narrowed its visibility); the message names the ids.
    """
    ids = [str(gpu_id).strip() for gpu_id in gpu_ids]
    if not ids:
        raise RuntimeError("the fit runs on CUDA but Ray gave its task no GPU (give --gpus-per-fit, e.g. 1 or 0.5)")
    if device_count < 1:
        raise RuntimeError(f"Ray gave this task GPU {','.join(ids)}, but CUDA shows this worker none "
                           f"(CUDA_VISIBLE_DEVICES={visible_devices!r})")
    visible = _visible_list(visible_devices)
    if visible == ids:  # narrowed by Ray: the task's GPUs are the only ones, in its order
        if device_count != len(ids):
            raise RuntimeError(f"Ray gave this task GPU {','.join(ids)} (CUDA_VISIBLE_DEVICES={visible_devices}), "
                               f"but CUDA shows this worker {device_count} GPUs: CUDA was initialized in the worker "
                               "before Ray chose its GPU, so cuda:0 need not be the GPU it was given")
        return "cuda:0"
    known = visible if visible is not None else [str(index) for index in range(device_count)]
    if ids[0] not in known or known.index(ids[0]) >= device_count:
        raise RuntimeError(f"Ray gave this task GPU {ids[0]}, which is not among the GPUs this worker's CUDA "
                           f"shows (CUDA_VISIBLE_DEVICES={visible_devices!r}, {device_count} GPUs)")
    return f"cuda:{known.index(ids[0])}"


def use_cuda_device(device: str) -> None:
    """Make ``device`` (``"cuda:N"``) the current CUDA device of torch and Warp in this process (kernels run on
    their tensors' device anyway; this covers allocations that name no device)."""
    import torch
    import warp as wp

    from warpavatar._src.warp_utils import init_warp

    torch.cuda.set_device(torch.device(device))
    init_warp()
    wp.set_device(device)


def _uuid_text(uuid) -> str:
    """A CUDA device UUID as ``nvidia-smi -L`` prints it: ``GPU-`` and the hex groups, lower case."""
    text = str(uuid).strip().lower()
    return "GPU-" + (text[4:] if text.startswith("gpu-") else text)


def describe_cuda_device(device: str) -> dict:
    """The GPU behind ``device`` (``"cuda:N"``) as torch and Warp see it.

    Returns:
        ``{"device": "cuda:N", "name": ..., "uuid": "GPU-...", "memory_gib": ...}`` (the UUID as ``nvidia-smi
        -L`` prints it).

    Raises:
        RuntimeError: torch's and Warp's device of that ordinal are different GPUs (their UUIDs differ).
    """
    import torch
    import warp as wp

    from warpavatar._src.warp_utils import init_warp

    index = torch.device(device).index or 0
    properties = torch.cuda.get_device_properties(index)
    torch_uuid = _uuid_text(properties.uuid)
    init_warp()
    warp_uuid = getattr(wp.get_device(f"cuda:{index}"), "uuid", None)
    if warp_uuid is not None and _uuid_text(warp_uuid) != torch_uuid:
        raise RuntimeError(f"torch's and Warp's {device} are different GPUs ({torch_uuid} and "
                           f"{_uuid_text(warp_uuid)}): set CUDA_DEVICE_ORDER the same for both")
    return {"device": device, "name": properties.name, "uuid": torch_uuid,
            "memory_gib": round(properties.total_memory / 2**30, 1)}


@functools.lru_cache(maxsize=None)
def _kernel_source_digest() -> str:
    """A digest of the Warp kernel sources (``warpavatar.kernels``) and of Warp's version."""
    import warp as wp

    from warpavatar import kernels

    digest = hashlib.sha256(wp.config.version.encode())
    for path in sorted(Path(kernels.__file__).parent.glob("*.py")):
        digest.update(path.name.encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()[:16]


def compiled_marker_name(device_kind: str) -> str:
    """The file in the kernel cache that records that a fit compiled this code's kernels there for
    ``device_kind`` (``cpu`` or ``sm_90``: a GPU's compute capability)."""
    return f"warpavatar-compiled-{device_kind}-{_kernel_source_digest()}"


@contextlib.contextmanager
def first_compile_turn(cache_dir: str | os.PathLike | None, device_kind: str) -> Iterator[None]:
    """While active, this process is the one fit on its host that compiles the kernels, when they have not been
    compiled into ``cache_dir`` for ``device_kind`` yet.

    Where the cache records that they were (:func:`compiled_marker_name`), it does nothing. Otherwise it waits
    for the host's other fits that hold their turn (an exclusive lock on a file in ``cache_dir``; the operating
    system releases it when a process dies), looks again, and holds the turn until the block ends; a block that
    ends without an exception records the kernels as compiled. A cache directory that cannot be written, or a
    file system without locks, makes it do nothing: the fits then compile side by side, as Warp allows.
    """
    if cache_dir is None:
        yield
        return
    cache_dir = Path(cache_dir)
    marker = cache_dir / compiled_marker_name(device_kind)
    if marker.exists():
        yield
        return
    try:
        import fcntl

        cache_dir.mkdir(parents=True, exist_ok=True)
        lock = open(cache_dir / f"warpavatar-compile-{device_kind}.lock", "a")
    except (ImportError, OSError):
        yield
        return
    with lock:
        try:
            fcntl.flock(lock, fcntl.LOCK_EX)
        except OSError:
            yield
            return
        try:
            if marker.exists():  # compiled by the fit that held the turn before
                fcntl.flock(lock, fcntl.LOCK_UN)
                yield
                return
            yield
            with contextlib.suppress(OSError):
                marker.touch()
        finally:
            with contextlib.suppress(OSError, ValueError):
                fcntl.flock(lock, fcntl.LOCK_UN)


def device_kind(device: str) -> str:
    """What a kernel is compiled for on ``device``: ``cpu``, or ``sm_XY`` (the GPU's compute capability)."""
    import torch

    device = torch.device(device)
    if device.type != "cuda":
        return "cpu"
    major, minor = torch.cuda.get_device_capability(device)
    return f"sm_{major}{minor}"


def kernel_cache_dir() -> Path:
    """This process's Warp kernel cache directory (Warp is initialized first, which fixes it)."""
    import warp as wp

    from warpavatar._src.warp_utils import init_warp

    init_warp()
    return Path(wp.config.kernel_cache_dir)
