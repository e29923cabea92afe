"""Image files read and written byte-safely, with OpenCV's and its codecs' own messages kept off stderr.

OpenCV takes a path as UTF-8 text: a path holding bytes that are not UTF-8 (which Python keeps as surrogate
escapes) crashes it with a segmentation fault. So images are read and written here through Python's file
objects, and OpenCV only decodes or encodes memory (``cv2.imdecode``, ``cv2.imencode``); video files, which
OpenCV must open itself, are refused first by :func:`check_opencv_path`.

OpenCV's log and FFmpeg's are turned off when this module is imported (unless ``OPENCV_LOG_LEVEL`` or
``OPENCV_FFMPEG_LOGLEVEL`` say otherwise), and libpng and libjpeg, which print their warnings from C straight to
file descriptor 2, decode with that descriptor pointed at the null device (:func:`native_stderr_silenced`): a
command's one-line error is then the only line on stderr.
"""

from __future__ import annotations

import contextlib
import os
import struct
import sys
import threading
from collections.abc import Iterator, Sequence

_USER_LOG_LEVEL = "OPENCV_LOG_LEVEL" in os.environ
os.environ.setdefault("OPENCV_LOG_LEVEL", "SILENT")  # read when cv2 is imported
os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")  # AV_LOG_QUIET, read when a video is first opened

import cv2  # noqa: E402  (after the variables above)
import numpy as np  # noqa: E402

from warpavatar.io.output_files import write_bytes_atomic  # noqa: E402

if not _USER_LOG_LEVEL:  # cv2 may have been imported before the variable was set
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)

__all__ = ["MAX_IMAGE_SIDE", "MAX_IMAGE_PIXELS", "ImageFileError", "decode_image", "read_image", "write_image",
           "check_opencv_path", "shown_path", "native_stderr_silenced"]

MAX_IMAGE_SIDE = 65536
"""The widest and tallest image read [pixels]; a larger size in a file's header is refused before decoding."""

MAX_IMAGE_PIXELS = 2**30
"""The most pixels an image read may have (OpenCV's own limit), checked in the header before decoding."""

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# JPEG start-of-frame markers (C0-CF less DHT C4, JPG C8 and DAC CC): their segment holds the image size
_JPEG_FRAME_MARKERS = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}


class ImageFileError(ValueError):
    """An image file that cannot be read or written.

    Attributes:
        path: the file.
        problem: what is wrong, in words.
    """

    def __init__(self, path: str | os.PathLike, problem: str):
        self.path = path
        self.problem = problem
        super().__init__(f"{shown_path(path)}: {problem}")

    def __reduce__(self):
        return (type(self), (self.path, self.problem))


def shown_path(path: str | os.PathLike) -> str:
    """``path`` as printable text: bytes that are not UTF-8 appear as ``\\xNN`` escapes."""
    return os.fsencode(path).decode("utf-8", "backslashreplace")


def check_opencv_path(path: str | os.PathLike, what: str = "") -> None:
    """Refuse a path that OpenCV cannot be given (one that is not valid UTF-8) before it crashes on it.

    Args:
        path: the file OpenCV is to open (a video to read or write).
        what: the option or role named first in the message (``"-o"``); empty: the path alone.

    Raises:
        ValueError: the path is not valid UTF-8 (the message names it and says what to do).
    """
    try:
        os.fspath(path).encode("utf-8")
    except UnicodeEncodeError:
        label = f"{what} " if what else ""
        raise ValueError(f"{label}{shown_path(path)}: the path is not valid UTF-8, which OpenCV needs to open a "
                         "video; rename the file or folder") from None


_silence_lock = threading.Lock()
_silence_users = 0
_saved_stderr: int | None = None


@contextlib.contextmanager
def native_stderr_silenced() -> Iterator[None]:
    """While active, file descriptor 2 (where C libraries print) goes to the null device.

    Counted across threads: the first to enter points it away, the last to leave restores it, so decoding on
    several threads at once is safe. Python's own writes to ``sys.stderr`` from any thread meanwhile are lost
    too; use it around a library call only. Does nothing where descriptor 2 is not open.
    """
    global _silence_users, _saved_stderr
    with _silence_lock:
        if _silence_users == 0:
            try:
                sys.stderr.flush()
                saved = os.dup(2)
            except (OSError, ValueError, AttributeError):  # no descriptor 2, or sys.stderr closed or None
                saved = None
            if saved is not None:
                null = os.open(os.devnull, os.O_WRONLY)
                os.dup2(null, 2)
                os.close(null)
            _saved_stderr = saved
        _silence_users += 1
    try:
        yield
    finally:
        with _silence_lock:
            _silence_users -= 1
            if _silence_users == 0 and _saved_stderr is not None:
                os.dup2(_saved_stderr, 2)
                os.close(_saved_stderr)
                _saved_stderr = None


def _header_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) from a PNG's IHDR or a JPEG's start-of-frame segment, or None (another format, or a
    header too short to say)."""
    if data.startswith(_PNG_SIGNATURE):
        if len(data) >= 24 and data[12:16] == b"IHDR":
            return struct.unpack(">II", data[16:24])
        return None
    if not data.startswith(b"\xff\xd8"):
        return None
    position = 2
    while position + 4 <= len(data):
        if data[position] != 0xFF:
            return None  # not at a marker: leave it to the decoder
        marker = data[position + 1]
        if marker == 0xFF:  # fill byte
            position += 1
            continue
        if marker == 0x01 or 0xD0 <= marker <= 0xD9:  # markers without a segment
            position += 2
            continue
        length = struct.unpack(">H", data[position + 2:position + 4])[0]
        if marker in _JPEG_FRAME_MARKERS:
            if position + 9 > len(data):
                return None
            height, width = struct.unpack(">HH", data[position + 5:position + 9])
            return width, height
        if marker == 0xDA:  # start of scan: no frame header before it
            return None
        position += 2 + length
    return None


def decode_image(path: str | os.PathLike, *, flags: int = cv2.IMREAD_UNCHANGED | cv2.IMREAD_IGNORE_ORIENTATION
                 ) -> np.ndarray:
    """An image file as OpenCV decodes it (channels in BGR(A) order, 8- or 16-bit, as ``flags`` ask).

    The file is read by Python (any path works) and its size, where a PNG or JPEG header gives it, is checked
    against :data:`MAX_IMAGE_SIDE` and :data:`MAX_IMAGE_PIXELS` before any pixel is decoded; the codecs'
    warnings are silenced (:func:`native_stderr_silenced`).

    Args:
        path: the image file.
        flags: ``cv2.IMREAD_*`` flags (default: as stored, EXIF orientation ignored).

    Returns:
        The pixels, [H, W] or [H, W, C].

    Raises:
        ImageFileError: the file cannot be read, is too large, or does not decode (the message names it).
    """
    try:
        with open(os.fspath(path), "rb") as stream:
            data = stream.read()
    except OSError as error:
        raise ImageFileError(path, f"cannot be read ({error.strerror or error})") from None
    size = _header_size(data)
    if size is not None:
        width, height = size
        if width > MAX_IMAGE_SIDE or height > MAX_IMAGE_SIDE or width * height > MAX_IMAGE_PIXELS:
            raise ImageFileError(path, f"its header says {width}x{height} pixels, more than an image may have "
                                       f"({MAX_IMAGE_SIDE} a side, {MAX_IMAGE_PIXELS} in all): corrupt or not a frame")
    if not data:
        raise ImageFileError(path, "cannot be read as an image (the file is empty)")
    try:
        with native_stderr_silenced():
            image = cv2.imdecode(np.frombuffer(data, np.uint8), flags)
    except cv2.error as error:
        detail = str(error).strip().splitlines()[-1] if str(error).strip() else "OpenCV error"
        raise ImageFileError(path, f"cannot be decoded as an image ({detail})") from None
    if image is None or image.size == 0:
        raise ImageFileError(path, "cannot be read as an image (unreadable or corrupt)")
    return image


def read_image(path: str | os.PathLike) -> np.ndarray:
    """An image file as RGB uint8 [H, W, 3]: grey is replicated, 16-bit rounded to 8 bits, alpha dropped.

    Raises:
        ImageFileError: as :func:`decode_image`, or pixels that are neither 8- nor 16-bit.
    """
    image = decode_image(path, flags=cv2.IMREAD_ANYDEPTH | cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
    if image.dtype == np.uint16:
        image = np.round(image / 257.0).astype(np.uint8)
    elif image.dtype != np.uint8:
        raise ImageFileError(path, f"must be an 8- or 16-bit image, got {image.dtype}")
    return np.ascontiguousarray(image[..., ::-1])


def write_image(path: str | os.PathLike, image: np.ndarray, *, params: Sequence[int] = (),
                fsync: bool = True) -> None:
    """Write an image file, its format chosen by the path's extension (``.png``, ``.jpg``, ...).

    The pixels are encoded in memory and the bytes written by Python (any path works), through a temporary name
    that is renamed once complete (:func:`~warpavatar.io.output_files.write_bytes_atomic`; ``fsync``: sync it
    first, off for files of a staged folder): a write that fails leaves nothing, and a full disk is one
    :class:`~warpavatar.io.output_files.DiskFullError` naming the file and its size.

    Args:
        path: the file to write (its folder must exist).
        image: RGB [H, W, 3], RGBA [H, W, 4] or grey [H, W], uint8 (or uint16 where the format allows).
        params: OpenCV's ``cv2.IMWRITE_*`` pairs, e.g. ``(cv2.IMWRITE_PNG_COMPRESSION, 9)``.

    Raises:
        ImageFileError: an image of another shape or type, or an extension OpenCV cannot encode.
        OSError: the file cannot be written.
    """
    image = np.asarray(image)
    if image.dtype not in (np.uint8, np.uint16) or not (image.ndim == 2 or (image.ndim == 3
                                                                           and image.shape[2] in (1, 3, 4))):
        raise ImageFileError(path, f"cannot be written from an array of shape {list(image.shape)} and type "
                                   f"{image.dtype}: expected RGB, RGBA or grey, uint8 or uint16")
    if image.ndim == 3 and image.shape[2] == 3:
        image = image[..., ::-1]
    elif image.ndim == 3 and image.shape[2] == 4:
        image = image[..., [2, 1, 0, 3]]
    extension = os.path.splitext(os.fspath(path))[1]
    try:
        ok, encoded = cv2.imencode(extension, np.ascontiguousarray(image), list(params))
    except cv2.error:
        ok = False
    if not ok:
        raise ImageFileError(path, f"OpenCV cannot write {extension or 'extension-less'} images of this kind")
    write_bytes_atomic(path, encoded, fsync=fsync)
