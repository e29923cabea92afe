"""The subjects of a batch: where each one's training folder is, what it is called, where its fit goes, and
whether an earlier run finished it."""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

__all__ = ["BatchSubject", "read_subjects", "read_subject_list", "finished_result", "DONE_NAME"]

#: the done marker in a subject's output folder: written atomically after its ``avatar.pt``; holds the result
DONE_NAME = "fit-many.json"


@dataclass(frozen=True)
class BatchSubject:
    """One subject of a batch.

    Attributes:
        name: the subject's name: its folder's name (also the name of its output folder).
        path: the folder as given (absolute): a subject root holding ``train/`` (and ``novel_view/*``,
            ``novel_pose/*``), or a video folder itself.
    """

    name: str
    path: Path

    @property
    def subject_root(self) -> Path | None:
        """The subject root when :attr:`path` holds ``train/``, else None (a bare video folder)."""
        return self.path if (self.path / "train").is_dir() else None

    @property
    def training_folder(self) -> Path:
        """The video folder the fit trains on: ``train/`` of a subject root, else :attr:`path` itself."""
        root = self.subject_root
        return root / "train" if root is not None else self.path

    def output(self, out_root: str | os.PathLike) -> Path:
        """The subject's output folder: ``out_root/<name>``."""
        return Path(out_root) / self.name


def read_subject_list(path: str | os.PathLike) -> list[Path]:
    """The folders a subject list names: a UTF-8 text file, one existing folder a line (blank lines and lines
    starting with ``#`` are skipped; a relative path is relative to the list file's folder).

    Raises:
        ValueError: the file cannot be read, or a line that is not UTF-8 text or names no folder (a binary or a
            JSON file given as a list); the message names the file and the first bad line.
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as error:
        raise ValueError(f"{path}: the subject list cannot be read ({error.strerror or error})") from None
    folders = []
    for number, raw in enumerate(data.splitlines(), start=1):
        try:
            line = raw.decode("utf-8-sig" if number == 1 else "utf-8").strip()
        except UnicodeDecodeError:
            line = None
        if line is None or "\0" in line:
            raise ValueError(f"{path}: line {number} is not UTF-8 text: a subject list is a text file naming one "
                             "subject or video folder a line (# starts a comment)")
        if not line or line.startswith("#"):
            continue
        entry = Path(line).expanduser()
        folder = entry if entry.is_absolute() else path.parent / entry
        if not folder.is_dir():
            raise ValueError(f"{path}: line {number} ({line[:60]!r}) names no folder: a subject list names one "
                             "existing subject or video folder a line (# starts a comment)")
        folders.append(folder)
    return folders


def read_subjects(arguments: list[str | os.PathLike]) -> list[BatchSubject]:
    """The subjects named on the command line, in order.

    Each argument is a subject folder, or a subject list file (:func:`read_subject_list`), whose folders are
    checked to exist. A folder argument that does not exist is kept: its fit fails alone, with the reader's
    error, in the batch's summary.

    Raises:
        ValueError: a list file that is not a list of folders, no subjects, or two subjects with the same folder
            name (their outputs would collide); the message names the file, or both paths.
    """
    paths: list[Path] = []
    for argument in arguments:
        argument = Path(argument)
        if argument.is_file():
            paths.extend(read_subject_list(argument))
        else:
            paths.append(argument)
    if not paths:
        raise ValueError("no subjects given (the list files are empty)")
    subjects: dict[str, BatchSubject] = {}
    for path in paths:
        # absolute() not resolve(): a symbolic link keeps its own name as the subject's name
        path = Path(os.path.normpath(path.expanduser().absolute()))
        subject = BatchSubject(name=path.name, path=path)
        if subject.name in subjects:
            if subjects[subject.name].path == path:
                raise ValueError(f"{path}: the subject is given twice")
            raise ValueError(f"two subjects are called {subject.name!r} ({subjects[subject.name].path} and {path}): "
                             "their outputs would share one folder; rename one of the folders")
        subjects[subject.name] = subject
    return list(subjects.values())


def finished_result(output: str | os.PathLike) -> dict | None:
    """The result an earlier run recorded for a finished fit in ``output`` (its done marker, with the fit's
    ``config``, when both it and ``avatar.pt`` exist), or None."""
    output = Path(output)
    marker = output / DONE_NAME
    if not (marker.is_file() and (output / "avatar.pt").is_file()):
        return None
    try:
        result = json.loads(marker.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None  # a marker that cannot be read does not prove the fit finished
    return result if isinstance(result, dict) and isinstance(result.get("config"), dict) else None
