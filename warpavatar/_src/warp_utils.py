"""Glue between torch tensors and Warp arrays, shared by every op of :mod:`warpavatar.ops`.

Rules every bridge follows:
    * tensors are handed to Warp as ``wp.from_torch(tensor.detach().contiguous())``, never with Warp's own
      gradient tracking: backward passes are explicit kernels called from ``torch.autograd.Function``;
    * kernels run on the device of their inputs and, on CUDA, on torch's current stream
      (:func:`torch_stream_scope`), so they order correctly with the surrounding torch work;
    * Warp is initialized lazily and quietly the first time an op runs.
"""

from __future__ import annotations

import contextlib
import functools

import torch
import warp as wp

# Quiet from the start (no banner, no module-load lines): some Warp calls initialize the runtime implicitly,
# before init_warp() runs.
wp.config.log_level = wp.LOG_WARNING

__all__ = [
    "init_warp",
    "warp_device",
    "to_warp",
    "torch_stream_scope",
    "warp_stream_of",
    "available_devices",
    "check_tensor",
]


@functools.lru_cache(maxsize=None)
def init_warp() -> None:
    """Initialize Warp once, without its start-up banner."""
    wp.init()


def warp_device(device: torch.device | str) -> str:
    """Warp's name for a torch device (``"cpu"`` or ``"cuda:N"``)."""
    device = torch.device(device)
    if device.type == "cpu":
        return "cpu"
    if device.type == "cuda":
        index = device.index if device.index is not None else torch.cuda.current_device()
        return f"cuda:{index}"
    raise ValueError(f"warpavatar kernels run on CPU or CUDA tensors, got a tensor on {device}")


def to_warp(tensor: torch.Tensor, dtype=None) -> wp.array:
    """View a torch tensor as a Warp array without copying (a contiguous copy is made only if needed).

    Args:
        tensor: any torch tensor on CPU or CUDA; it is detached first, so Warp never records it.
        dtype: Warp dtype of one element (e.g. ``wp.vec3``); by default inferred from the tensor's dtype.
    """
    init_warp()
    tensor = tensor.detach()
    if not tensor.is_contiguous():
        tensor = tensor.contiguous()
    if dtype is None:
        return wp.from_torch(tensor, requires_grad=False)
    return wp.from_torch(tensor, dtype=dtype, requires_grad=False)


_WARP_STREAMS: dict[tuple[str, int], wp.Stream] = {}


def warp_stream_of(stream: torch.cuda.Stream) -> wp.Stream:
    """The one Warp wrapper of a torch CUDA stream, made on first use and kept for the process.

    Warp registers an external stream by its handle, without a count, when a wrapper is made, and forgets it when
    any wrapper of that handle is garbage-collected, together with a CUDA graph capture under way on it (the
    capture then ends in "unknown capture stream"). One lasting wrapper per handle keeps the registration, and
    saves making one per launch. Torch's streams come from fixed pools, so the table stays small.
    """
    init_warp()
    key = (str(stream.device), int(stream.cuda_stream))
    wrapper = _WARP_STREAMS.get(key)
    if wrapper is None:
        wrapper = _WARP_STREAMS[key] = wp.stream_from_torch(stream)
    return wrapper


@contextlib.contextmanager
def torch_stream_scope(device: torch.device | str):
    """Run the Warp launches inside this block on torch's current stream of ``device``.

    On CPU it only selects the Warp device.
    """
    init_warp()
    device = torch.device(device)
    name = warp_device(device)
    if device.type == "cuda":
        stream = warp_stream_of(torch.cuda.current_stream(device))
        with wp.ScopedDevice(name), wp.ScopedStream(stream, sync_enter=False):
            yield name
    else:
        with wp.ScopedDevice(name):
            yield name


def available_devices() -> list[str]:
    """Torch device names on which both torch and Warp can run: ``"cpu"`` and every visible CUDA device."""
    devices = ["cpu"]
    if torch.cuda.is_available():
        init_warp()
        if wp.is_cuda_available():
            devices += [f"cuda:{index}" for index in range(torch.cuda.device_count())]
    return devices


def check_tensor(name: str, tensor, shape: tuple, *, dtype_kind: str = "float", device=None) -> None:
    """Raise a clear ``ValueError``/``TypeError`` when ``tensor`` does not have the expected layout.

    Args:
        name: argument name shown in the message.
        tensor: the value to check.
        shape: expected shape; ``None`` entries accept any size, ``-1`` is also a wildcard.
        dtype_kind: ``"float"`` (a floating-point dtype), ``"float32"`` (exactly float32: inputs Warp reads in
            place, without a copy) or ``"int"`` (an integer dtype).
        device: when given, the device the tensor must be on.
    """
    if not isinstance(tensor, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(tensor).__name__}")
    if tensor.dim() != len(shape) or any(
        expected not in (None, -1) and actual != expected for actual, expected in zip(tensor.shape, shape)
    ):
        pretty = "[" + ", ".join("*" if s in (None, -1) else str(s) for s in shape) + "]"
        raise ValueError(f"{name} must have shape {pretty}, got {list(tensor.shape)}")
    if dtype_kind == "float" and not tensor.is_floating_point():
        raise TypeError(f"{name} must be a floating-point tensor, got {tensor.dtype}")
    if dtype_kind == "float32" and tensor.dtype != torch.float32:
        raise TypeError(f"{name} must be float32 (the Warp kernels are single precision), got {tensor.dtype}")
    if dtype_kind == "int" and (tensor.is_floating_point() or tensor.is_complex()):
        raise TypeError(f"{name} must be an integer tensor, got {tensor.dtype}")
    if device is not None and tensor.device != torch.device(device):
        raise ValueError(f"{name} is on {tensor.device} but the other inputs are on {device}")
