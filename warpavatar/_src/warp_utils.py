"""Glue between torch tensors and Warp arrays, shared by every op of :mod:`warpavatar.ops`.

Rules every bridge follows:
    * tensors are handed to Warp without a copy and never with Warp's own gradient tracking (backward passes
      are explicit kernels called from ``torch.autograd.Function``): as ``wp.array`` views (:func:`to_warp`,
      what ``wp.from_torch`` makes, for about 70 % of its host cost), or, for kernel arguments on a hot path,
      as the
      launch descriptors Warp passes to kernels (:func:`warp_descriptor`, a fifth of ``wp.from_torch``'s
      cost);
    * Warp's sort and scan get the tensors' pointers (:func:`radix_sort_pairs`, :func:`inclusive_scan`);
    * kernels run on the device of their inputs and, on CUDA, on torch's current stream
      (:func:`torch_stream_scope`), so they order correctly with the surrounding torch work;
    * Warp is initialized lazily and quietly the first time an op runs; on a machine without the NVIDIA driver
      (CPU only) it is initialized when this module is imported, with the native library's "Could not find or
      load the NVIDIA CUDA driver" line discarded (:func:`init_warp`).
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import os
import sys

import torch
import warp as wp

# Quiet from the start (no banner, no module-load lines): some Warp calls initialize the runtime implicitly,
# before init_warp() runs.
wp.config.log_level = wp.LOG_WARNING

__all__ = [
    "init_warp",
    "warp_device",
    "to_warp",
    "warp_descriptor",
    "write_only_descriptor",
    "torch_stream_scope",
    "warp_stream_of",
    "current_stream_handle",
    "native_entry",
    "warp_context",
    "available_devices",
    "check_tensor",
    "radix_sort_pairs",
    "inclusive_scan",
]


@functools.lru_cache(maxsize=None)
def init_warp() -> None:
    """Initialize Warp once, without its start-up banner and, where the NVIDIA driver cannot be loaded, without
    the warning its native library prints about it (a CPU-only machine is a supported one)."""
    if _CUDA_DRIVER_LOADABLE:
        wp.init()
        return
    with _native_stderr_discarded():
        wp.init()


def _cuda_driver_loadable() -> bool:
    """Whether this process can load the NVIDIA driver library, as Warp's native start-up looks for it."""
    names = ("nvcuda.dll",) if sys.platform == "win32" else ("libcuda.so", "libcuda.so.1")
    for name in names:
        try:
            ctypes.CDLL(name)
        except OSError:
            continue
        return True
    return False


@contextlib.contextmanager
def _native_stderr_discarded():
    """While active, whatever native code writes to file descriptor 2 is discarded (Python's own ``sys.stderr``
    is flushed first); without a usable descriptor 2 it does nothing."""
    if sys.stderr is not None:
        sys.stderr.flush()
    try:
        saved = os.dup(2)
    except OSError:
        yield
        return
    discard = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(discard, 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        os.close(discard)


# Warp's native start-up prints the driver warning from whichever call initializes it first (wp.get_device,
# wp.launch, ...), so on a machine without the driver it is initialized here, once and quietly (about 50 ms).
_CUDA_DRIVER_LOADABLE = _cuda_driver_loadable()
if not _CUDA_DRIVER_LOADABLE:
    init_warp()


def warp_device(device: torch.device | str) -> str:
    """Warp's name for a torch device (``"cpu"`` or ``"cuda:N"``)."""
    device = torch.device(device)
    if device.type == "cpu":
        return "cpu"
    if device.type == "cuda":
        index = device.index if device.index is not None else torch.cuda.current_device()
        return f"cuda:{index}"
    raise ValueError(f"warpavatar kernels run on CPU or CUDA tensors, got a tensor on {device}")


# Scalar Warp dtypes a torch dtype's memory may be read as (integers as signed or unsigned); the first is the
# default view.
_WARP_SCALARS_OF_TORCH = {
    torch.float32: (wp.float32,),
    torch.float64: (wp.float64,),
    torch.float16: (wp.float16,),
    torch.bfloat16: (wp.bfloat16,),
    torch.int32: (wp.int32, wp.uint32),
    torch.int64: (wp.int64, wp.uint64),
    torch.int16: (wp.int16, wp.uint16),
    torch.int8: (wp.int8, wp.uint8),
    torch.uint8: (wp.uint8, wp.int8),
    torch.bool: (wp.bool, wp.uint8, wp.int8),
}


@functools.lru_cache(maxsize=None)
def _element_layout(torch_dtype: torch.dtype, dtype) -> tuple[object, tuple[int, ...], int]:
    """(Warp dtype, trailing tensor dimensions one element takes, its size in bytes) of a tensor of
    ``torch_dtype`` read as elements of ``dtype`` (None: the default scalar); raises when they do not fit."""
    scalars = _WARP_SCALARS_OF_TORCH.get(torch_dtype)
    if scalars is None:
        raise TypeError(f"Warp kernels cannot read {torch_dtype} tensors")
    if dtype is None:
        dtype = scalars[0]
    if getattr(dtype, "_wp_scalar_type_", dtype) not in scalars:
        raise TypeError(f"cannot view a {torch_dtype} tensor as Warp {dtype.__name__}")
    return dtype, tuple(getattr(dtype, "_shape_", ())), _item_bytes(dtype)


def _item_bytes(dtype) -> int:
    """Bytes of one element of a Warp scalar, vector or matrix dtype."""
    item_bytes = ctypes.sizeof(dtype._type_)
    for size in getattr(dtype, "_shape_", ()):
        item_bytes *= size
    return item_bytes


_LAYOUTS: dict[tuple, tuple[object, tuple[int, ...], tuple[int, ...]]] = {}
_LAYOUTS_KEPT = 4096  # distinct (dtype, shape) entries kept before the table starts over


def _array_layout(tensor: torch.Tensor, dtype) -> tuple[object, tuple[int, ...], tuple[int, ...]]:
    """(Warp dtype, Warp shape, contiguous byte strides) of a contiguous ``tensor`` read as elements of
    ``dtype`` (vector and matrix dtypes take the last dimensions); remembered per torch dtype, dtype and shape,
    as a kernel's bridge sees the same few every call."""
    key = (tensor.dtype, dtype, tensor.shape)
    layout = _LAYOUTS.get(key)
    if layout is not None:
        return layout
    dtype, inner_shape, item_bytes = _element_layout(tensor.dtype, dtype)
    shape = tuple(tensor.shape)
    if inner_shape:
        if shape[len(shape) - len(inner_shape):] != inner_shape:
            raise ValueError(f"cannot view a tensor of shape {list(shape)} as Warp {dtype.__name__} "
                             f"(its last dimensions must be {list(inner_shape)})")
        shape = shape[: len(shape) - len(inner_shape)] or (1,)
    elif not shape:
        shape = (1,)
    strides = [item_bytes] * len(shape)
    for axis in range(len(shape) - 1, 0, -1):
        strides[axis - 1] = strides[axis] * shape[axis]
    if len(_LAYOUTS) >= _LAYOUTS_KEPT:
        _LAYOUTS.clear()
    layout = _LAYOUTS[key] = (dtype, shape, tuple(strides))
    return layout


_WARP_DEVICES: dict[torch.device, object] = {}


def _warp_device_object(device: torch.device):
    found = _WARP_DEVICES.get(device)
    if found is None:
        init_warp()
        found = _WARP_DEVICES[device] = wp.get_device(warp_device(device))
    return found



def to_warp(tensor: torch.Tensor, dtype=None) -> wp.array:
    """View a torch tensor as a Warp array without copying (a contiguous copy is made only if needed).

    Args:
        tensor: any torch tensor on CPU or CUDA; it is detached first, so Warp never records it.
        dtype: Warp dtype of one element (e.g. ``wp.vec3``); by default inferred from the tensor's dtype.

    Returns:
        A ``wp.array`` over the tensor's memory (without gradient), which keeps the tensor alive.
    """
    tensor = tensor.detach()
    if not tensor.is_contiguous():
        tensor = tensor.contiguous()
    dtype, shape, strides = _array_layout(tensor, dtype)
    # The pointer constructor costs half of wp.from_torch (which also resolves gradients and the storage's capacity).
    array = wp.array(ptr=tensor.data_ptr(), dtype=dtype, shape=shape, strides=strides,
                     device=_warp_device_object(tensor.device), copy=False)
    array._tensor = tensor
    return array


@functools.lru_cache(maxsize=None)
def _array_descriptor_type() -> type:
    """The ctypes structure Warp passes to a kernel for an array (what ``wp.from_torch(..., return_ctype=True)``
    builds)."""
    init_warp()
    return type(wp.from_torch(torch.zeros(1), return_ctype=True))


def warp_descriptor(tensor: torch.Tensor, dtype=None):
    """The launch-argument descriptor of a contiguous torch tensor: what ``wp.launch`` passes to the kernel for
    a ``wp.array`` argument, made without building the array (about 1.5 us on the host against 5-10 us).

    Use it for kernel arguments only (``wp.launch`` and launchers that read ``shape``/``ndim``); the
    ``warp.utils`` algorithms (scan, sort) need :func:`to_warp`'s arrays. The launch runs on Warp's current
    device (:func:`torch_stream_scope`), which must be the tensor's.

    Args:
        tensor: a contiguous torch tensor on CPU or CUDA (not copied, not detached: Warp never records it).
        dtype: Warp dtype of one element (e.g. ``wp.vec3``, taking the tensor's last dimension); by default
            the scalar of the tensor's dtype.

    Returns:
        A ``warp.types.array_t`` (``shape[i]``, ``ndim``) that keeps the tensor alive.

    Raises:
        ValueError: the tensor is not contiguous, or its last dimensions do not make elements of ``dtype``.
        TypeError: its scalar type is not ``dtype``'s.
    """
    if not tensor.is_contiguous():
        raise ValueError(f"warp_descriptor needs a contiguous tensor, got strides {tensor.stride()}")
    key = (tensor.dtype, dtype, tensor.shape)
    template = _DESCRIPTOR_TEMPLATES.get(key)
    if template is None:
        _, shape, strides = _array_layout(tensor, dtype)
        if len(_DESCRIPTOR_TEMPLATES) >= _LAYOUTS_KEPT:
            _DESCRIPTOR_TEMPLATES.clear()
        template = _DESCRIPTOR_TEMPLATES[key] = _array_descriptor_type()(0, 0, len(shape), shape, strides)
    # A copy of the layout's template with the pointer set: a quarter of the structure constructor's cost.
    descriptor = _array_descriptor_type().from_buffer_copy(template)
    descriptor.data = tensor.data_ptr()
    descriptor._tensor = tensor
    return descriptor


# Launch descriptors without a pointer, per (torch dtype, Warp dtype, shape): warp_descriptor copies them.
_DESCRIPTOR_TEMPLATES: dict[tuple, ctypes.Structure] = {}


def write_only_descriptor(sink: torch.Tensor, element_count: int, dtype):
    """A launch descriptor of ``element_count`` elements of ``dtype`` that all lie at the start of ``sink``
    (stride 0), for an output a kernel must be given but whose values nobody reads: the forward outputs that an
    adjoint launch (``wp.launch(..., adjoint=True)``) writes again while it computes the gradients, whose
    adjoints read only the gradient arrays. Every thread writes the same bytes, so they hold no meaning; the
    buffer costs one element instead of ``element_count``.

    Args:
        sink: a contiguous tensor of at least one element of ``dtype`` (its bytes), on the launch's device; kept
            alive by the descriptor.
        element_count: the length the kernel sees (``shape[0]``).
        dtype: Warp dtype of one element (e.g. ``wp.vec3``).

    Raises:
        ValueError: ``sink`` is not contiguous or smaller than one element.
    """
    item_bytes = _item_bytes(dtype)
    if not sink.is_contiguous() or sink.numel() * sink.element_size() < item_bytes:
        raise ValueError(f"the sink of a write-only {dtype.__name__} array must be a contiguous tensor of at least "
                         f"{item_bytes} bytes, got {sink.numel() * sink.element_size()}")
    descriptor = _array_descriptor_type()(sink.data_ptr(), 0, 1, (element_count,), (0,))
    descriptor._tensor = sink
    return descriptor


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


_RAW_STREAM = getattr(torch._C, "_cuda_getCurrentRawStream", None)


def current_stream_handle(device: torch.device) -> int:
    """The ``cudaStream_t`` of torch's current stream on CUDA ``device``, as an int (what
    ``torch.cuda.current_stream(device).cuda_stream`` gives, without making the stream object: a fifth of its
    host cost, through the binding torch's own compiled code calls)."""
    index = device.index if device.index is not None else torch.cuda.current_device()
    if _RAW_STREAM is not None:
        return _RAW_STREAM(index)
    return torch.cuda.current_stream(index).cuda_stream


class torch_stream_scope:
    """Run the Warp launches inside this block on torch's current stream of ``device``.

    On CPU it only selects the Warp device. ``with torch_stream_scope(device) as name:`` gives Warp's name of the
    device. The Warp device of a torch device with an index is looked up once; the stream is torch's current
    one at entry.
    """

    __slots__ = ("_device", "_scopes")

    def __init__(self, device: torch.device | str):
        self._device = device if isinstance(device, torch.device) else torch.device(device)
        self._scopes = ()

    def __enter__(self) -> str:
        device = self._device
        warp_device_object = _warp_device_object(device) if device.index is not None or device.type == "cpu" else (
            _warp_device_object(torch.device("cuda", torch.cuda.current_device())))
        if device.type == "cuda":
            stream = warp_stream_of(torch.cuda.current_stream(device))
            self._scopes = (wp.ScopedDevice(warp_device_object), wp.ScopedStream(stream, sync_enter=False))
        else:
            self._scopes = (wp.ScopedDevice(warp_device_object),)
        for scope in self._scopes:
            scope.__enter__()
        return warp_device_object.alias

    def __exit__(self, *exc) -> None:
        for scope in reversed(self._scopes):
            scope.__exit__(*exc)
        self._scopes = ()


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
    actual = tensor.shape
    matches = len(actual) == len(shape)
    if matches:  # a plain loop: this runs on every call of every op (a generator costs twice as much)
        for size, expected in zip(actual, shape):
            if size != expected and expected is not None and expected != -1:
                matches = False
                break
    if not matches:
        pretty = "[" + ", ".join("*" if s in (None, -1) else str(s) for s in shape) + "]"
        raise ValueError(f"{name} must have shape {pretty}, got {list(actual)}")
    if dtype_kind == "float":
        if not tensor.is_floating_point():
            raise TypeError(f"{name} must be a floating-point tensor, got {tensor.dtype}")
    elif dtype_kind == "float32":
        if tensor.dtype != torch.float32:
            raise TypeError(f"{name} must be float32 (the Warp kernels are single precision), got {tensor.dtype}")
    elif dtype_kind == "int" and (tensor.is_floating_point() or tensor.is_complex()):
        raise TypeError(f"{name} must be an integer tensor, got {tensor.dtype}")
    if device is not None and tensor.device != device:
        if not isinstance(device, torch.device) and tensor.device == torch.device(device):
            return
        raise ValueError(f"{name} is on {tensor.device} but the other inputs are on {device}")


@functools.lru_cache(maxsize=None)
def _runtime_core():
    """Warp's native library (``warp._src.context.runtime.core``), or None where this Warp lays it out otherwise."""
    init_warp()
    try:
        from warp._src.context import runtime  # noqa: PLC0415

        return runtime.core
    except Exception:  # noqa: BLE001 (any other layout)
        return None


@functools.lru_cache(maxsize=None)
def native_entry(name: str):
    """Warp's native function ``name`` (what Warp's public functions end in), looked up once; None where this Warp
    version lays its runtime out otherwise (callers then use the public function)."""
    core = _runtime_core()
    return None if core is None else getattr(core, name, None)


# Warp's native sort and scan entry points, called with the tensors' pointers: what ``wp.utils.radix_sort_pairs``
# and ``wp.utils.array_scan`` end in, without building a ``wp.array`` for each operand (about 7 us of host time
# each). Where this Warp version lays them out otherwise, the public functions are used.
_SORT_AND_SCAN_ENTRIES = ("wp_radix_sort_pairs_float_device", "wp_radix_sort_pairs_float_host",
                          "wp_radix_sort_pairs_int_device", "wp_radix_sort_pairs_int_host",
                          "wp_array_scan_int_device", "wp_array_scan_int_host")


@functools.lru_cache(maxsize=None)
def _native_core():
    if all(native_entry(name) is not None for name in _SORT_AND_SCAN_ENTRIES):
        return _runtime_core()
    return None


def warp_context(device: torch.device):
    """Warp's CUDA context handle of torch ``device`` (the device looked up once)."""
    return _warp_device_object(device).context


_SORT_KEY_SUFFIX = {torch.float32: "float", torch.int32: "int"}


def radix_sort_pairs(keys: torch.Tensor, values: torch.Tensor, count: int, *, begin_bit: int, end_bit: int) -> None:
    """Sort the first ``count`` (key, value) pairs by key, stably, in place, as ``wp.utils.radix_sort_pairs``.

    Args:
        keys: contiguous float32 or int32 tensor of at least ``2 * count`` elements (the second half is the
            sort's scratch space).
        values: contiguous tensor of at least ``2 * count`` elements of 4 or 8 bytes each (e.g. int32 [2 N] or
            int32 [2 N, 2]), on the same device.
        count: pairs to sort.
        begin_bit, end_bit: the key bits sorted on.

    Runs on Warp's current device and stream (:class:`torch_stream_scope`).
    """
    if count == 0 or begin_bit == end_bit:
        return
    value_bytes = values.element_size() * (values[0].numel() if values.dim() > 1 else 1)
    suffix = _SORT_KEY_SUFFIX.get(keys.dtype)
    if (suffix is None or value_bytes not in (4, 8) or not keys.is_contiguous() or not values.is_contiguous()
            or keys.numel() < 2 * count or values.shape[0] < 2 * count):
        raise ValueError(f"radix_sort_pairs: keys must be contiguous float32 or int32 and both arrays hold "
                         f"2 * {count} elements of 4 or 8 bytes, got {keys.dtype} {list(keys.shape)} and "
                         f"{values.dtype} {list(values.shape)}")
    core = _native_core()
    if core is None:
        words = values.view(torch.int32)  # the values as 4-byte words: one or two an element
        typed = to_warp(words.view(-1), wp.int32) if value_bytes == 4 else to_warp(words.view(-1, 2), wp.vec2i)
        wp.utils.radix_sort_pairs(to_warp(keys), typed, count, begin_bit=begin_bit, end_bit=end_bit)
        return
    where = "device" if keys.is_cuda else "host"
    getattr(core, f"wp_radix_sort_pairs_{suffix}_{where}")(keys.data_ptr(), values.data_ptr(), count, begin_bit,
                                                           end_bit, value_bytes)


def inclusive_scan(values: torch.Tensor, out: torch.Tensor, *, stride: int = 1) -> None:
    """``out[i] = sum(values[0 : (i + 1) * stride : stride])``: the inclusive prefix sum of every ``stride``-th
    int32 of ``values``, starting with the first, as ``wp.utils.array_scan`` computes it.

    Args:
        values: int32 tensor whose storage, from its first element, holds ``out.numel()`` values ``stride``
            elements apart (e.g. the second column of a contiguous [N, 2] tensor's view that starts at it).
        out: contiguous int32 tensor receiving the sums, on the same device.
        stride: elements between consecutive values.

    Runs on Warp's current device and stream (:class:`torch_stream_scope`).
    """
    count = out.numel()
    if count == 0:
        return
    if values.dtype != torch.int32 or out.dtype != torch.int32 or not out.is_contiguous():
        raise ValueError(f"inclusive_scan needs int32 tensors (a contiguous output), got {values.dtype} and "
                         f"{out.dtype}")
    if values.untyped_storage().nbytes() // 4 - values.storage_offset() < (count - 1) * stride + 1:
        raise ValueError(f"inclusive_scan: {count} values {stride} apart do not fit in the input's storage")
    core = _native_core()
    if core is None:
        source = wp.array(ptr=values.data_ptr(), dtype=wp.int32, shape=(count,), strides=(4 * stride,),
                          device=_warp_device_object(values.device), copy=False)
        wp.utils.array_scan(source, to_warp(out), inclusive=True)
        return
    where = "device" if values.is_cuda else "host"
    ok = getattr(core, f"wp_array_scan_int_{where}")(values.data_ptr(), out.data_ptr(), count, 4 * stride, 4, 1, True)
    if values.is_cuda and not ok:
        raise RuntimeError("Warp's scan failed on the device")
