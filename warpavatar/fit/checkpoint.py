"""Fit checkpoints: one file, written atomically, holding the core's state and each extension's by name."""

from __future__ import annotations

import os
import threading
from collections import OrderedDict
from pathlib import Path

import torch

__all__ = ["CHECKPOINT_NAME", "CHECKPOINT_FORMAT", "save_checkpoint", "read_checkpoint", "CheckpointWriter"]

CHECKPOINT_NAME = "checkpoint.pt"
CHECKPOINT_FORMAT = "warpavatar-checkpoint/2"


def save_checkpoint(path: str | os.PathLike, state: dict) -> Path:
    """Write ``state`` (with the format tag) to ``path`` through a temporary file and a rename."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    torch.save({"format": CHECKPOINT_FORMAT, **state}, tmp)
    os.replace(tmp, path)
    return path


def read_checkpoint(path: str | os.PathLike, *, mmap: bool = False) -> dict:
    """Read a checkpoint written by :func:`save_checkpoint`.

    Args:
        path: the file.
        mmap: map the tensors' storage from the file instead of reading it (for a look at the small entries,
            such as ``step``, of a checkpoint that may hold hundreds of MB).

    Raises:
        ValueError: an unreadable file, or one of another format (named in the message).
    """
    path = Path(path)
    try:
        state = torch.load(path, map_location="cpu", weights_only=False, mmap=mmap)
    except Exception as error:  # noqa: BLE001 - any unreadable file gets the same clear message
        raise ValueError(f"{path}: cannot read the checkpoint ({error})") from error
    found = state.get("format", "warpavatar-checkpoint/1") if isinstance(state, dict) else None
    if found != CHECKPOINT_FORMAT:
        raise ValueError(f"{path}: checkpoint format {found!r} was written by an earlier warpavatar (this one resumes "
                         f"{CHECKPOINT_FORMAT!r}); start the fit again in a new output folder (a finished fit's "
                         "avatar.pt still loads)")
    return state


def _host_copy(value):
    """``value`` with every tensor in it (in dicts, lists, tuples) copied to host memory, detached."""
    if isinstance(value, torch.Tensor):
        return value.detach().to("cpu", copy=True)
    if isinstance(value, dict):  # a module's state dict is an OrderedDict whose _metadata its loading reads
        copied = (OrderedDict if isinstance(value, OrderedDict) else dict)(
            (key, _host_copy(item)) for key, item in value.items())
        if hasattr(value, "_metadata"):
            copied._metadata = value._metadata
        return copied
    if isinstance(value, tuple) and hasattr(value, "_fields"):  # a named tuple
        return type(value)(*(_host_copy(item) for item in value))
    if isinstance(value, (list, tuple)):
        return type(value)(_host_copy(item) for item in value)
    return value


class CheckpointWriter:
    """Writes a fit's checkpoints while its training goes on: the state is first copied to host memory (a snapshot
    that later steps cannot change), then saved and renamed (:func:`save_checkpoint`) on a thread of its own.
    One write at a time; a write that failed raises at the next :meth:`save` or :meth:`wait`."""

    def __init__(self):
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None

    def save(self, path: str | os.PathLike, state: dict, *, wait: bool = False) -> None:
        """Write ``state`` to ``path``: in the background, or before returning with ``wait``."""
        self.wait()
        snapshot = _host_copy(state)
        if wait:
            save_checkpoint(path, snapshot)
            return
        self._thread = threading.Thread(target=self._write, args=(Path(path), snapshot), name="checkpoint writer")
        self._thread.start()

    def _write(self, path: Path, snapshot: dict) -> None:
        try:
            save_checkpoint(path, snapshot)
        except BaseException as error:  # noqa: BLE001 - handed to the training thread at its next call
            self._error = error

    def wait(self) -> None:
        """Wait for the write under way, if any.

        Raises:
            whatever the last background write raised (an OSError, torch's RuntimeError for a missing folder).
        """
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        error, self._error = self._error, None
        if error is not None:
            raise error
