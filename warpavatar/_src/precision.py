"""TF32 for the float32 GEMMs of the avatar's MLPs on CUDA: an explicit choice, switched on only where they run.

TF32 tensor cores multiply float32 matrices with 10-bit mantissas (inputs rounded to about 3 decimal digits,
sums kept in float32), at several times the GEMM throughput of full float32 on Ampere and later GPUs. The MLPs
of a training step and of playback (the skinning field's, the pose correction's) are where that pays, and where
the rounding is one more source of noise in a stochastic fit (what it costs in quality is for whole fits to
measure, against ``--matmul-precision fp32``); the rest of posing keeps float32 (bone transforms composed by matmuls, where a
relative error of 5e-4 moves a 2 m body by a millimetre), so TF32 is not switched on for the whole process.
Instead:

- the trainer and the :class:`~warpavatar.model.playback.Player` run their work inside
  :func:`mlp_precision` (the ``--matmul-precision`` choice), which records the precision for the MLPs;
- each MLP evaluation runs inside :func:`mlp_matmuls`, which sets torch's cuBLAS flag to the recorded precision
  for that evaluation and restores it afterwards (outside any :func:`mlp_precision` block, in evaluation or
  exports, it changes nothing: torch's own setting applies);
- a training step's backward pass, whose GEMMs are nearly all the MLPs' gradients, runs inside
  :func:`matmul_precision` with the same choice (the gradients' products in TF32 too).

A CUDA graph records the kernels chosen when it is captured, so the captured step and the captured playback
frame run their MLPs in the precision in force during the capture: the same blocks, so the same choice. On a CPU
nothing changes (torch's flag is left alone).
"""

from __future__ import annotations

import contextlib
import contextvars
from typing import Iterator

import torch

__all__ = ["MATMUL_PRECISIONS", "check_matmul_precision", "matmul_precision", "mlp_precision", "mlp_matmuls",
           "float32_sums", "mlp_dtype", "current_mlp_dtype"]

MATMUL_PRECISIONS = ("tf32", "fp32")
"""The accepted precisions of float32 GEMMs: ``tf32`` (TF32 tensor cores on CUDA) or ``fp32`` (full float32)."""

_mlp_precision: contextvars.ContextVar[str | None] = contextvars.ContextVar("warpavatar_mlp_precision", default=None)
_mlp_dtype: contextvars.ContextVar[torch.dtype | None] = contextvars.ContextVar("warpavatar_mlp_dtype", default=None)


def check_matmul_precision(precision: str) -> str:
    """``precision`` when it is one of :data:`MATMUL_PRECISIONS`.

    Raises:
        ValueError: any other value.
    """
    if precision not in MATMUL_PRECISIONS:
        raise ValueError(f"matmul precision must be 'tf32' or 'fp32', got {precision!r}")
    return precision


@contextlib.contextmanager
def matmul_precision(precision: str, device) -> Iterator[None]:
    """Float32 matmuls in ``precision`` inside the block when ``device`` is a CUDA device: torch's cuBLAS flag
    (``torch.backends.cuda.matmul.fp32_precision``, ``allow_tf32`` before torch 2.9) is set, and restored to
    what it was on leaving. Elsewhere it changes nothing (no CPU library's flag is touched).

    The setting is global to the process, not to the thread: it also reaches autograd's backward threads while
    the block runs (a ``loss.backward()`` inside it computes its GEMMs in ``precision``).
    """
    check_matmul_precision(precision)
    if torch.device(device).type != "cuda":
        yield
        return
    flags = torch.backends.cuda.matmul
    if hasattr(flags, "fp32_precision"):  # torch >= 2.9: cuBLAS's own setting ("none": the global one's)
        before = flags.fp32_precision
        flags.fp32_precision = "tf32" if precision == "tf32" else "ieee"
        try:
            yield
        finally:
            flags.fp32_precision = before
    else:
        before = flags.allow_tf32
        flags.allow_tf32 = precision == "tf32"
        try:
            yield
        finally:
            flags.allow_tf32 = before


@contextlib.contextmanager
def mlp_precision(precision: str) -> Iterator[None]:
    """Run the avatar's MLPs (every :func:`mlp_matmuls` block) in ``precision`` inside this block (on CUDA).
    Outside any such block the MLPs run under torch's own setting, untouched. Nests; the previous choice is
    restored on leaving."""
    token = _mlp_precision.set(check_matmul_precision(precision))
    try:
        yield
    finally:
        _mlp_precision.reset(token)


def mlp_matmuls(device) -> contextlib.AbstractContextManager:
    """The block in which an MLP on ``device`` runs: :func:`matmul_precision` with the precision that the
    enclosing :func:`mlp_precision` chose; outside any, nothing changes."""
    precision = _mlp_precision.get()
    return contextlib.nullcontext() if precision is None else matmul_precision(precision, device)


@contextlib.contextmanager
def float32_sums(device) -> Iterator[None]:
    """Float16 GEMMs on ``device`` keep their sums in float32 inside the block: on CUDA, cuBLAS's reduced-precision
    reductions (``torch.backends.cuda.matmul.allow_fp16_reduced_precision_reduction``, on by default, which lets
    split-K sums round to float16) are switched off, and restored on leaving. Elsewhere nothing changes (CPU
    float16 GEMMs sum in float32). Like :func:`matmul_precision`, a CUDA graph keeps the kernels chosen while
    it is captured."""
    flags = torch.backends.cuda.matmul
    if torch.device(device).type != "cuda" or not hasattr(flags, "allow_fp16_reduced_precision_reduction"):
        yield
        return
    before = flags.allow_fp16_reduced_precision_reduction
    flags.allow_fp16_reduced_precision_reduction = False
    try:
        yield
    finally:
        flags.allow_fp16_reduced_precision_reduction = before


@contextlib.contextmanager
def mlp_dtype(dtype: torch.dtype) -> Iterator[None]:
    """Mark the block as a playback frame (:class:`~warpavatar.model.playback.Player`) whose parts' MLPs run in
    ``dtype`` (``torch.float16`` or ``torch.float32``) where they prepared for it
    (:meth:`~warpavatar.model.parts.AvatarPart.prepare_playback`): :func:`current_mlp_dtype`. Outside any such
    block parts compute as a fit does. Nests; restored on leaving."""
    token = _mlp_dtype.set(dtype)
    try:
        yield
    finally:
        _mlp_dtype.reset(token)


def current_mlp_dtype() -> torch.dtype | None:
    """The dtype the enclosing :func:`mlp_dtype` block chose, or None outside playback frames."""
    return _mlp_dtype.get()
