"""Safe outputs: every file and folder the project writes goes through this module.

Four guarantees, for every writer (the CLIs' outputs, avatars, checkpoints, video folders, exports):

* **Atomic and unique.** A file is written under a temporary name of its own in the same folder
  (:func:`temporary_path`: ``NAME.tmp-<pid>-<random hex>``) and renamed into place once complete
  (:func:`atomic_path`, :func:`atomic_open`, :func:`write_bytes_atomic`); a folder is assembled the same way
  (:func:`staged_folder`). On any error only that temporary path is removed: cleanup never touches a name the
  process did not create, and two writers never share a temporary name.
* **Only the project's own folders are replaced.** Each output folder the project creates holds a marker file,
  :data:`OUTPUT_MARKER_NAME`, naming its kind (``render-frames``, ``eval-renders``, ``video-folder``, ``fit``) and,
  for staged folders, every entry written. An existing folder is replaced only when that marker says it is an
  output of the same kind and it holds nothing else (:func:`check_replaceable_folder`); a user's folder is
  refused, whatever the options. Outputs equal to the working directory, one of its ancestors, the file system
  root or the home folder are refused (:func:`check_output_location`).
* **One writer per output.** :func:`output_lock` holds an advisory ``flock`` on a hidden file beside the output
  (:func:`lock_path`), which records the holder's pid and host; a second writer gets :class:`OutputBusyError`.
* **A full disk is one clear error.** ENOSPC and EDQUOT become :class:`DiskFullError`, whose message names the
  output, the bytes being written (when known) and the free space; nothing is left under a temporary or final
  name.

Streams from :func:`atomic_open` write through ``os.write``, so tests can simulate a full disk by patching it.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import io
import json
import os
import re
import secrets
import shutil
import socket
from collections.abc import Iterator
from pathlib import Path

__all__ = ["OUTPUT_MARKER_NAME", "DiskFullError", "OutputBusyError", "temporary_path", "is_temporary_name",
           "remove_leftover_temporaries", "is_disk_full", "disk_full_error", "atomic_path", "atomic_open",
           "write_bytes_atomic", "write_text_atomic", "write_json_atomic", "append_text", "check_output_location",
           "read_output_marker", "mark_output_folder", "check_replaceable_folder", "staged_folder", "lock_path",
           "output_lock"]

OUTPUT_MARKER_NAME = ".warpavatar-output"
"""The file in every output folder the project creates: its kind on the first line, then (for staged folders)
the relative path of every entry written, one a line."""

_DISK_FULL_ERRNOS = (errno.ENOSPC, errno.EDQUOT)
_TEMPORARY_TAG = re.compile(r"\.(tmp|old)-\d+-[0-9a-f]{12}")
_LOCK_TEXT = re.compile(r"pid (\d+) on (\S+)")


class DiskFullError(OSError):
    """A write that failed because its file system is full (ENOSPC) or the user's disk quota is spent (EDQUOT);
    ``errno`` says which. Its message is one line naming the output."""


class OutputBusyError(OSError):
    """Another process holds the output's lock (:func:`output_lock`); the message names the output and the
    holder's pid and host."""


# --------------------------------------------------------------------------------------------------------
# Temporary names and full disks


def temporary_path(final: str | os.PathLike, *, suffix: str | None = None, tag: str = "tmp") -> Path:
    """A fresh temporary name beside ``final``, unique to this process and call.

    Args:
        final: the path the temporary file or folder will be renamed to.
        suffix: None: ``NAME.tmp-<pid>-<hex>``; a suffix such as ``".usdc"``: ``STEM.tmp-<pid>-<hex>.usdc``, for
            libraries that pick the format from the name's ending.
        tag: the word in the name: ``tmp`` for what is being written, ``old`` for a folder moved aside.

    Returns:
        the temporary path, in ``final``'s folder (so the rename is atomic); nothing exists there yet.
    """
    final = Path(final)
    unique = f"{tag}-{os.getpid()}-{secrets.token_hex(6)}"
    name = f"{final.name}.{unique}" if suffix is None else f"{final.stem}.{unique}{suffix}"
    return final.parent / name


def is_temporary_name(name: str, final_name: str) -> bool:
    """Whether ``name`` is a temporary name that :func:`temporary_path` gives for a final name ``final_name``
    (with or without a kept suffix)."""
    stem, suffix = os.path.splitext(final_name)
    return any(re.fullmatch(re.escape(prefix) + _TEMPORARY_TAG.pattern + re.escape(ending), name)
               for prefix, ending in ((final_name, ""), (stem, suffix)))


def remove_leftover_temporaries(folder: str | os.PathLike, final_names) -> list[str]:
    """Remove the temporary files and folders (:func:`temporary_path`'s names) of ``final_names`` in ``folder``
    that a writer killed before it could clean up left there. Call it only while holding the outputs' lock
    (:func:`output_lock`), when no other writer can be using them. Returns the names removed."""
    folder = Path(folder)
    try:
        names = sorted(entry.name for entry in folder.iterdir())
    except OSError:
        return []
    removed = [name for name in names if any(is_temporary_name(name, final) for final in final_names)]
    for name in removed:
        _remove_temporary(folder / name)
    return removed


def is_disk_full(error: BaseException) -> bool:
    """Whether ``error`` is an OSError for a full file system or a spent disk quota."""
    return isinstance(error, OSError) and error.errno in _DISK_FULL_ERRNOS


def _size_text(count: int) -> str:
    value = float(count)
    for unit in ("bytes", "KiB", "MiB", "GiB"):
        if value < 1024 or unit == "GiB":
            return f"{int(value)} bytes" if unit == "bytes" else f"{value:.1f} {unit}"
        value /= 1024
    raise AssertionError("unreachable")


def _free_space(path: Path) -> int | None:
    for folder in (path, *path.parents):
        try:
            return shutil.disk_usage(folder).free
        except OSError:
            continue
    return None


def disk_full_error(path: str | os.PathLike, code: int = errno.ENOSPC, *, needed: int | None = None,
                    part: str | None = None) -> DiskFullError:
    """The one-line error for a write of ``path`` that ran out of space.

    Args:
        path: the output that was not written (a file, or a folder being assembled).
        code: ``errno.ENOSPC`` or ``errno.EDQUOT``.
        needed: bytes that were being written [bytes], when known.
        part: the file inside a folder output that was being written, when there is one.
    """
    path = Path(path)
    reason = "the disk quota is exceeded" if code == errno.EDQUOT else "no space is left on the disk"
    details = []
    if part is not None:
        details.append(f"writing {part}")
    if needed is not None:
        details.append(f"{_size_text(needed)} to write")
    free = _free_space(path.parent)
    if free is not None:
        details.append(f"{_size_text(free)} free in {path.parent}")
    error = DiskFullError(f"{path}: not written: {reason} ({', '.join(details)}); free some space or write it "
                          "elsewhere")
    error.errno, error.path, error.needed = code, path, needed
    return error


def _as_disk_full(final: Path, error: BaseException) -> DiskFullError | None:
    """``error`` as a :class:`DiskFullError` naming ``final`` (None when it is no full-disk error)."""
    if isinstance(error, DiskFullError) or not is_disk_full(error):
        return None
    return disk_full_error(final, error.errno)


def _remove_temporary(path: Path) -> None:
    """Remove a temporary file or folder this process created (nothing else is ever passed here)."""
    try:
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path, ignore_errors=True)
        else:
            path.unlink(missing_ok=True)
    except OSError:
        pass


def _fsync_path(path: Path) -> None:
    descriptor = os.open(path, os.O_RDONLY)
    try:
        os.fsync(descriptor)
    finally:
        os.close(descriptor)


def _fsync_folder(folder: Path) -> None:
    try:
        _fsync_path(folder)
    except OSError:  # some file systems cannot sync a folder; the rename is still atomic
        pass


# --------------------------------------------------------------------------------------------------------
# Atomic files


@contextlib.contextmanager
def atomic_path(final: str | os.PathLike, *, suffix: str | None = None, fsync: bool = True) -> Iterator[Path]:
    """Yield a fresh temporary path for a library to write ``final`` to; when the block ends normally, the
    temporary file is synced and renamed to ``final`` (an existing file there is replaced only then).

    On any error the temporary path alone is removed and ``final`` is left as it was; a full disk raises
    :class:`DiskFullError`. ``suffix``: see :func:`temporary_path`. ``fsync``: sync the file and its folder
    (off for files inside a folder that is itself staged).
    """
    final = Path(final)
    temporary = temporary_path(final, suffix=suffix)
    try:
        yield temporary
        if fsync:
            _fsync_path(temporary)
        os.replace(temporary, final)
        if fsync:
            _fsync_folder(final.parent)
    except BaseException as error:
        _remove_temporary(temporary)
        translated = _as_disk_full(final, error)
        if translated is not None:
            raise translated from None
        raise


class _DescriptorWriter(io.RawIOBase):
    """A binary stream over a file descriptor that writes through ``os.write`` and remembers the OSError of a
    failed write (libraries such as torch wrap it in their own exception)."""

    def __init__(self, descriptor: int):
        super().__init__()
        self._descriptor = descriptor
        self.error: OSError | None = None
        self.written = 0

    def writable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def fileno(self) -> int:
        return self._descriptor

    def write(self, data) -> int:
        view = memoryview(data).cast("B")
        done = 0
        try:
            while done < len(view):
                done += os.write(self._descriptor, view[done:])
        except OSError as error:
            self.error = error
            raise
        self.written += done
        return done

    def seek(self, offset: int, whence: int = os.SEEK_SET) -> int:
        return os.lseek(self._descriptor, offset, whence)

    def close(self) -> None:
        if not self.closed:
            super().close()
            os.close(self._descriptor)


@contextlib.contextmanager
def atomic_open(final: str | os.PathLike, mode: str = "wb", *, encoding: str = "utf-8",
                fsync: bool = True) -> Iterator[io.IOBase]:
    """Yield a new stream writing a temporary file that becomes ``final`` when the block ends normally (see
    :func:`atomic_path`). ``mode``: ``"wb"`` (binary) or ``"w"`` (text in ``encoding``).

    A failed write ends as :class:`DiskFullError` for a full disk (even where the library writing the stream
    turned the OSError into its own exception) and as the OSError otherwise.
    """
    if mode not in ("wb", "w"):
        raise ValueError(f"atomic_open writes new files: mode must be 'wb' or 'w', got {mode!r}")
    final = Path(final)
    with atomic_path(final, fsync=False) as temporary:
        raw = _DescriptorWriter(os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
        buffered = io.BufferedWriter(raw, buffer_size=1 << 20)
        stream = buffered if mode == "wb" else io.TextIOWrapper(buffered, encoding=encoding)
        try:
            yield stream
            stream.flush()
            if fsync:
                os.fsync(raw.fileno())
            stream.close()
        except BaseException as error:
            with contextlib.suppress(Exception):
                stream.close()
            raw.close()
            if raw.error is not None and isinstance(error, Exception) and error is not raw.error:
                raise raw.error from None  # the write's own error, which the library wrapped
            raise
        finally:
            raw.close()
    if fsync:
        _fsync_folder(final.parent)


def write_bytes_atomic(final: str | os.PathLike, data, *, fsync: bool = True) -> Path:
    """Write ``data`` (bytes-like) to ``final`` atomically; a full disk names the size being written."""
    final = Path(final)
    size = memoryview(data).nbytes
    try:
        with atomic_open(final, fsync=fsync) as stream:
            stream.write(data)
    except DiskFullError as error:
        raise disk_full_error(final, error.errno, needed=size) from None
    return final


def write_text_atomic(final: str | os.PathLike, text: str, *, fsync: bool = True) -> Path:
    """Write ``text`` (UTF-8) to ``final`` atomically."""
    return write_bytes_atomic(final, text.encode("utf-8"), fsync=fsync)


def write_json_atomic(final: str | os.PathLike, value, *, indent: int = 2, fsync: bool = True) -> Path:
    """Write ``value`` as indented JSON text (final newline) to ``final`` atomically."""
    return write_text_atomic(final, json.dumps(value, indent=indent) + "\n", fsync=fsync)


def append_text(path: str | os.PathLike, text: str) -> None:
    """Append ``text`` (UTF-8) to the log file ``path``; a full disk raises :class:`DiskFullError` naming it."""
    path = Path(path)
    try:
        with open(path, "a", encoding="utf-8") as stream:
            stream.write(text)
    except OSError as error:
        if is_disk_full(error):
            raise disk_full_error(path, error.errno, needed=len(text.encode("utf-8"))) from None
        raise


# --------------------------------------------------------------------------------------------------------
# Output locations and folders


def check_output_location(path: str | os.PathLike, flag: str | None = None) -> None:
    """Refuse an output that is the working directory, one of its ancestors (``..``, the file system root) or
    the home folder: writing an output there would replace the folder the user works in.

    Args:
        path: the output as given.
        flag: the option that gave it (``"-o"``), for the message.

    Raises:
        ValueError: one line naming the option, the path and what it is.
    """
    path = Path(path)
    resolved = Path(os.path.abspath(path)).resolve()
    cwd = Path.cwd().resolve()
    what = None
    if resolved == Path(resolved.anchor):
        what = "the file system root"
    elif resolved == cwd:
        what = "the working directory"
    elif resolved in cwd.parents:
        what = "an ancestor of the working directory"
    else:
        with contextlib.suppress(RuntimeError, KeyError):
            if resolved == Path.home().resolve():
                what = "the home folder"
    if what is not None:
        name = f"{flag} {path}" if flag else str(path)
        raise ValueError(f"{name}: is {what}; an output must not replace it: give a new path below it "
                         f"(e.g. {flag + ' ' if flag else ''}{path / 'warpavatar-out'})")


def read_output_marker(folder: str | os.PathLike) -> tuple[str, set[str] | None] | None:
    """The marker of an output folder: ``(kind, the relative paths written or None)``; None without a marker."""
    marker = Path(folder) / OUTPUT_MARKER_NAME
    try:
        lines = marker.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError):
        return None
    if not lines or not lines[0].strip():
        return None
    return lines[0].strip(), (set(lines[1:]) if len(lines) > 1 else None)


def mark_output_folder(folder: str | os.PathLike, kind: str, *, entries: list[str] | None = None) -> Path:
    """Create ``folder`` if needed and write its marker: ``kind`` and the ``entries`` written (relative paths),
    when listed. Returns the marker's path."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    text = "\n".join([kind, *(entries or [])]) + "\n"
    return write_text_atomic(folder / OUTPUT_MARKER_NAME, text, fsync=False)


def _folder_entries(folder: Path) -> list[str]:
    """Every file and folder below ``folder`` (without the marker), as sorted relative POSIX paths."""
    entries = []
    for root, folders, files in os.walk(folder):
        base = Path(root).relative_to(folder)
        entries += [(base / name).as_posix() for name in folders + files]
    return sorted(entry for entry in entries if entry != OUTPUT_MARKER_NAME)


def _shown(names: list[str]) -> str:
    return ", ".join(names[:4]) + (f" and {len(names) - 4} more" if len(names) > 4 else "")


def check_replaceable_folder(folder: str | os.PathLike, *, kind: str, overwrite: bool, name: str | None = None,
                             overwrite_hint: str = "--overwrite") -> bool:
    """Check that an output folder of ``kind`` may be written at ``folder``.

    A missing or empty folder may; an existing one only when its marker says it is an output of the same kind,
    it holds nothing but the entries that marker lists, and ``overwrite`` is given. A folder the project did not
    write is refused even with ``overwrite``: nothing of the user's is ever deleted.

    Args:
        folder: the output folder.
        kind: the kind of output to be written there (``"render-frames"``).
        overwrite: whether replacing an earlier output of this kind was asked for.
        name: how messages name the output (default: the path; a CLI passes ``"-o PATH"``).
        overwrite_hint: how messages say to replace it (``"--overwrite"``, ``"overwrite=True"``).

    Returns:
        whether a folder exists there (and is to be replaced).

    Raises:
        FileExistsError: one line saying why the folder is refused and what to do instead.
    """
    folder = Path(folder)
    name = name or str(folder)
    if folder.is_symlink():
        raise FileExistsError(f"{name}: is a symbolic link; give the folder it points to, or another path")
    if not folder.exists():
        return False
    if not folder.is_dir():
        raise FileExistsError(f"{name}: is a file; the output must be a folder")
    entries = _folder_entries(folder)
    marker = read_output_marker(folder)
    if not entries and marker is None:
        return True
    alternative = "choose another output" if name == str(folder) else f"choose another {name.split()[0]}"
    if marker is None:
        raise FileExistsError(f"{name}: the folder exists and holds files warpavatar did not write "
                              f"({_shown(entries)}); {alternative} (it is never replaced, even with {overwrite_hint})")
    found, written = marker
    if found != kind:
        raise FileExistsError(f"{name}: holds a warpavatar {found} output, not {kind}; {alternative}")
    foreign = [entry for entry in entries if written is None or entry not in written]
    if foreign:
        raise FileExistsError(f"{name}: holds files warpavatar did not write besides its {kind} "
                              f"({_shown(foreign)}); move them away or {alternative}")
    if not overwrite:
        raise FileExistsError(f"{name}: already exists (an earlier {kind} output); give {overwrite_hint} to replace "
                              f"it, or {alternative}")
    return True


@contextlib.contextmanager
def staged_folder(destination: str | os.PathLike, *, kind: str = "video-folder", overwrite: bool = False,
                  name: str | None = None, overwrite_hint: str = "overwrite=True") -> Iterator[Path]:
    """Write a folder atomically: yields a new empty temporary folder beside ``destination`` to write into; when
    the block ends normally it is marked as an output of ``kind`` (listing everything in it) and takes
    ``destination``'s place, otherwise it alone is removed.

    ``destination`` must be missing, empty, or (with ``overwrite``) an earlier output of the same kind holding
    nothing else (:func:`check_replaceable_folder`, checked on entry and again before the swap); the earlier
    folder is moved aside, the new one renamed into place, and only then the earlier one removed.

    Args:
        destination: the folder to create.
        kind: the output's kind, written to its marker (``"video-folder"``: the data writers').
        overwrite: replace an earlier output of this kind instead of raising FileExistsError.
        name, overwrite_hint: how messages name the folder and the way to replace it.

    Raises:
        FileExistsError: ``destination`` may not be replaced (see above).
        DiskFullError: the disk filled up; nothing was written at ``destination``.
    """
    destination = Path(destination)
    check = dict(kind=kind, overwrite=overwrite, name=name, overwrite_hint=overwrite_hint)
    check_replaceable_folder(destination, **check)
    destination.parent.mkdir(parents=True, exist_ok=True)
    staging = temporary_path(destination)
    staging.mkdir()
    try:
        yield staging
        mark_output_folder(staging, kind, entries=_folder_entries(staging))
        if check_replaceable_folder(destination, **check):
            aside = temporary_path(destination, tag="old")
            os.rename(destination, aside)
            try:
                os.rename(staging, destination)
            except BaseException:
                os.rename(aside, destination)
                raise
            shutil.rmtree(aside)  # checked just before: the project's own output, nothing else
        else:
            os.rename(staging, destination)
    except BaseException as error:
        _remove_temporary(staging)
        if is_disk_full(error):
            part = None
            with contextlib.suppress(ValueError, TypeError):  # the file inside the folder that was being written
                part = Path(getattr(error, "path", None) or error.filename).relative_to(staging).as_posix()
            raise disk_full_error(destination, error.errno, part=part,
                                  needed=getattr(error, "needed", None)) from None
        raise


# --------------------------------------------------------------------------------------------------------
# One writer per output


def lock_path(output: str | os.PathLike) -> Path:
    """The lock file of an output: ``.NAME.warpavatar-lock`` beside it."""
    output = Path(os.path.abspath(output))
    return output.parent / f".{output.name}.warpavatar-lock"


def _lock_holder(descriptor: int) -> str:
    with contextlib.suppress(OSError, UnicodeDecodeError):
        match = _LOCK_TEXT.search(os.pread(descriptor, 200, 0).decode("utf-8"))
        if match:
            return f"pid {match.group(1)} on {match.group(2)}"
    return "pid unknown"


@contextlib.contextmanager
def output_lock(output: str | os.PathLike, *, flag: str | None = None) -> Iterator[Path]:
    """Hold the lock of ``output`` (a file or folder) while the block runs, so that one process at a time writes
    it; the lock file (:func:`lock_path`) records this process's pid and host and is removed on release. The
    output's location is checked first (:func:`check_output_location`); once the lock is held, the temporary
    files an earlier writer of ``output`` left beside it when it was killed are removed
    (:func:`remove_leftover_temporaries`).

    Args:
        output: the output path.
        flag: the option that gave it (``"-o"``), for the messages.

    Raises:
        OutputBusyError: another process holds the lock (the message names it and its pid).
        ValueError: the output is a folder the user works in, or a file not written by the project is in the
            lock's place.
    """
    check_output_location(output, flag)
    path = lock_path(output)
    name = f"{flag} {output}" if flag else str(output)
    path.parent.mkdir(parents=True, exist_ok=True)
    while True:
        descriptor = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as error:
            holder = _lock_holder(descriptor)
            os.close(descriptor)
            if error.errno not in (errno.EWOULDBLOCK, errno.EAGAIN):
                raise OSError(f"{path}: cannot lock {name} ({error.strerror})") from None
            raise OutputBusyError(f"{name}: another warpavatar process ({holder}) is writing it; wait for it "
                                  f"to end or give another {flag or 'output'}") from None
        try:  # the holder may have released and removed the file between our open and flock: lock the new one
            same = os.path.samestat(os.fstat(descriptor), os.stat(path))
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(descriptor)
    try:
        text = os.pread(descriptor, 200, 0)
        if text and not _LOCK_TEXT.match(text.decode("utf-8", errors="replace")):
            raise ValueError(f"{path}: is in the place of {name}'s lock file but was not written by warpavatar; "
                             "move it away")
        os.ftruncate(descriptor, 0)
        os.pwrite(descriptor, f"pid {os.getpid()} on {socket.gethostname()}\n".encode(), 0)
    except BaseException:
        os.close(descriptor)
        raise
    try:
        remove_leftover_temporaries(path.parent, [Path(os.path.abspath(output)).name])
        yield path
    finally:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(path)  # while still holding the lock, so no one else holds one on this file
        os.close(descriptor)
