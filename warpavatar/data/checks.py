"""Small validators of video-folder files: each raises :class:`VideoFolderError` naming the offending file."""

from __future__ import annotations

import json
import math
import os
import zipfile
import zlib
from collections.abc import Mapping
from pathlib import Path

import numpy as np

__all__ = ["VideoFolderError", "RIGID_TOLERANCE", "float_array", "check_rigid", "check_intrinsics", "read_json",
           "read_npz", "require_mapping", "positive_int", "listed"]

RIGID_TOLERANCE = 1e-3
"""Largest entry of ``|R^T R - I|`` accepted for the rotation part of a rigid 4x4 transform."""

_LAST_ROW_TOLERANCE = 1e-5  # how far the last row of a rigid transform may be from [0, 0, 0, 1]
_LARGEST = float(np.finfo(np.float32).max)  # values are used as float32
_MAX_LISTED = 5  # at most this many offending ids or files are named in an error message


class VideoFolderError(ValueError):
    """A video folder, or one of its files, is missing or invalid.

    Attributes:
        path: the offending file or folder.
        problem: what is wrong with it, in words.
    """

    def __init__(self, path: str | os.PathLike, problem: str):
        self.path = Path(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")

    def __reduce__(self):
        return (type(self), (self.path, self.problem))


def float_array(value, shape: tuple[int, ...], path: Path, what: str) -> np.ndarray:
    """``value`` as a finite float64 array of exactly ``shape``."""
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise VideoFolderError(path, f"{what} must be numbers of shape {list(shape)}, got {value!r:.80}") from None
    if array.shape != shape:
        raise VideoFolderError(path, f"{what} must have shape {list(shape)}, got {list(array.shape)}")
    if not np.all(np.isfinite(array)):
        raise VideoFolderError(path, f"{what} holds non-finite values (nan or inf)")
    if array.size and np.abs(array).max() > _LARGEST:
        raise VideoFolderError(path, f"{what} holds a value beyond float32's range ({np.abs(array).max():.3g})")
    return array


def _index_text(index: tuple[int, ...], names: tuple[str, ...]) -> str:
    return ", ".join(f"{name} {value}" for name, value in zip(names, index))


def check_rigid(matrices: np.ndarray, path: Path, what: str, index_names: tuple[str, ...] = ()) -> None:
    """Check that ``matrices[..., 4, 4]`` are finite rigid transforms (rotation + translation)."""
    if not np.all(np.isfinite(matrices)):
        where = ""
        if index_names:
            bad = tuple(np.argwhere(~np.isfinite(matrices).all(axis=(-2, -1)))[0])
            where = f" (first at {_index_text(bad, index_names)})"
        raise VideoFolderError(path, f"{what} holds non-finite values (nan or inf){where}")
    matrices = matrices.astype(np.float64, copy=False)
    last_row_error = np.abs(matrices[..., 3, :] - np.array([0.0, 0.0, 0.0, 1.0])).max(axis=-1)
    rotation = matrices[..., :3, :3]
    gram = np.einsum("...ki,...kj->...ij", rotation, rotation)
    orthonormal_error = np.abs(gram - np.eye(3)).max(axis=(-2, -1))
    determinant = np.linalg.det(rotation)
    where = ""
    if np.any(last_row_error > _LAST_ROW_TOLERANCE):
        bad = tuple(np.argwhere(last_row_error > _LAST_ROW_TOLERANCE)[0])
        if index_names:
            where = f" (first at {_index_text(bad, index_names)})"
        raise VideoFolderError(path, f"{what} is not rigid: its last row is not [0, 0, 0, 1]{where}")
    if np.any(orthonormal_error > RIGID_TOLERANCE):
        bad = tuple(np.argwhere(orthonormal_error > RIGID_TOLERANCE)[0])
        if index_names:
            where = f" (first at {_index_text(bad, index_names)}: |R^T R - I| = {orthonormal_error[bad]:.3g})"
        raise VideoFolderError(
            path, f"{what} is not rigid: its rotation part is not orthonormal within {RIGID_TOLERANCE}{where}")
    if np.any(determinant <= 0.0):
        bad = tuple(np.argwhere(determinant <= 0.0)[0])
        if index_names:
            where = f" (first at {_index_text(bad, index_names)})"
        raise VideoFolderError(
            path, f"{what} is not rigid: its rotation part has determinant -1, a reflection{where}")


def check_intrinsics(K: np.ndarray, path: Path, what: str) -> None:
    if np.abs(K[2] - np.array([0.0, 0.0, 1.0])).max() > 1e-6:
        raise VideoFolderError(path, f"{what} must have the last row [0, 0, 1], got {K[2].tolist()}")
    if K[0, 0] <= 0.0 or K[1, 1] <= 0.0:
        raise VideoFolderError(path, f"{what} must have positive focal lengths, got fx={K[0, 0]}, fy={K[1, 1]}")


def read_json(path: Path):
    if not path.is_file():
        raise VideoFolderError(path, "file is missing")
    try:
        with open(path, encoding="utf-8") as stream:
            return json.load(stream)
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise VideoFolderError(path, f"cannot be read as JSON ({error})") from None
    except RecursionError:
        raise VideoFolderError(path, "cannot be read as JSON (nested too deeply)") from None


def require_mapping(value, path: Path, what: str) -> Mapping:
    if not isinstance(value, Mapping):
        raise VideoFolderError(path, f"{what} must be a JSON object, got {type(value).__name__}")
    return value


def positive_int(value, path: Path, what: str, *, at_most: int | None = None) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
            or value != int(value) or value <= 0:
        raise VideoFolderError(path, f"{what} must be a positive integer, got {value!r}")
    if at_most is not None and value > at_most:
        raise VideoFolderError(path, f"{what} must be at most {at_most}, got {value!r}")
    return int(value)


def listed(items) -> str:
    items = list(items)
    text = ", ".join(str(item) for item in items[:_MAX_LISTED])
    return text + (f" and {len(items) - _MAX_LISTED} more" if len(items) > _MAX_LISTED else "")



def read_npz(path: Path) -> dict[str, np.ndarray]:
    """Every array of an .npz archive (no pickles)."""
    if not path.is_file():
        raise VideoFolderError(path, "file is missing")
    try:
        with np.load(path, allow_pickle=False) as archive:
            return {key: archive[key] for key in archive.files}
    except (OSError, ValueError, zipfile.BadZipFile, zlib.error, EOFError) as error:
        raise VideoFolderError(path, f"cannot be read as an .npz archive ({error})") from None
