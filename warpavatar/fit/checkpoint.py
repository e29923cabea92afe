"""Fit checkpoints: one file, written atomically, holding the core's state and each extension's by name."""

from __future__ import annotations

import os
from pathlib import Path

import torch

__all__ = ["CHECKPOINT_NAME", "CHECKPOINT_FORMAT", "save_checkpoint", "read_checkpoint"]

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
