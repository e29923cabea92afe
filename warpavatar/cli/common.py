"""Pieces shared by the command-line tools: device choice and turning expected errors into clear messages."""

from __future__ import annotations

import functools
import sys

import torch

__all__ = ["default_device", "resolve_device", "friendly_errors"]


def default_device() -> str:
    return "cuda" if torch.cuda.is_available() else "cpu"


def resolve_device(name: str) -> torch.device:
    device = torch.device(name)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise SystemExit("error: --device cuda was asked for but torch sees no CUDA device")
    return device


def friendly_errors(main):
    """Report input errors (bad files, bad values) as one line on stderr with exit status 2, no traceback."""

    @functools.wraps(main)
    def wrapper(argv=None):
        try:
            return main(argv)
        except (ValueError, FileNotFoundError, NotADirectoryError, PermissionError) as error:
            print(f"error: {error}", file=sys.stderr)
            return 2
        except KeyboardInterrupt:
            print("interrupted", file=sys.stderr)
            return 130

    return wrapper
