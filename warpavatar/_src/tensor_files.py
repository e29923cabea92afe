"""Reading the project's torch files (the avatar file, the fit checkpoint) without running anything in them.

``torch.load`` unpickles, and a pickle can call any function it names. Every file warpavatar writes holds only
tensors and plain containers (dict, list, tuple, str, int, float, bool, None), so it is read with
``weights_only=True``: torch's restricted unpickler rebuilds exactly those and refuses anything else before it
runs. A refusal becomes one line naming the file, and so does a file that holds something other than a dict.
"""

from __future__ import annotations

import os
import pickle
import re
import warnings
import zipfile
from pathlib import Path

import torch

__all__ = ["read_tensor_file"]


def read_tensor_file(path: str | os.PathLike, *, what: str, mmap: bool = False) -> dict:
    """The dict that ``torch.save`` wrote to ``path``, read on the CPU with ``weights_only=True``.

    Args:
        path: the file.
        what: what the file is, for the messages (``"avatar file"``, ``"checkpoint"``).
        mmap: map the tensors' storage from the file instead of reading it (a file in torch's zip layout;
            another is read whole).

    Raises:
        ValueError: the file holds objects other than tensors and plain containers (it was not loaded: nothing
            in it ran), cannot be read, or holds something other than a dict; one line naming ``path``.
    """
    path = Path(path)
    try:
        with warnings.catch_warnings():  # torch warns about the pickle protocol of files it reads fine
            warnings.simplefilter("ignore")
            state = torch.load(path, map_location="cpu", weights_only=True, mmap=mmap and zipfile.is_zipfile(path))
    except pickle.UnpicklingError as error:
        raise ValueError(f"{path}: the {what} holds objects other than tensors and plain containers "
                         f"({_refusal(str(error))}) and was not loaded (nothing in it ran)") from None
    except OSError as error:
        raise ValueError(f"{path}: cannot read the {what} ({error.strerror or error})") from None
    except Exception as error:  # noqa: BLE001 - whatever else torch raises, the file is not one it wrote whole
        reason = " ".join(f"{type(error).__name__}: {error}".split()).rstrip(":")
        raise ValueError(f"{path}: cannot read the {what}: not a file that torch.save wrote, or a damaged one "
                         f"({reason})") from None
    if not isinstance(state, dict):
        raise ValueError(f"{path}: not a warpavatar {what}: it holds a {type(state).__name__}, not a dict")
    return state


def _refusal(message: str) -> str:
    """What torch's restricted unpickler refused, in a few words, from its long message."""
    if found := re.search(r"GLOBAL (\S+) was not an allowed global", message):
        return f"a reference to {found.group(1)}"
    if found := re.search(r"Unsupported operand (\d+)", message):
        return f"pickle opcode {found.group(1)}"
    return "refused by torch's weights-only unpickler"
