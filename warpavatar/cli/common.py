"""Pieces shared by the command-line tools: device choice, the avatar and motion options, and turning expected
errors into clear messages."""

from __future__ import annotations

import argparse
import contextlib
import functools
import math
import os
import signal
import sys
import warnings
from pathlib import Path

import torch

# imported by every command, before any other module imports cv2: OpenCV's and FFmpeg's own log lines go off
from warpavatar.io.images import shown_path
from warpavatar.signals import (STOP_SIGNALS, Interrupted, StopRequest, interruption_exit_status,
                                interruption_signal, stop_on_signals, termination_interrupts)

__all__ = ["default_device", "resolve_device", "cpu_torch_settings", "ArgumentParser", "positive_number",
           "check_output_path", "one_line_warnings", "friendly_errors", "avatar_parser", "load_avatar",
           "load_motion_for", "training_motion_path", "TRAINING_MOTION_HELP",
           # re-exported from warpavatar.signals
           "Interrupted", "STOP_SIGNALS", "interruption_signal", "interruption_exit_status",
           "termination_interrupts", "StopRequest", "stop_on_signals"]


def default_device() -> str:
    return "cuda" if torch.cuda.is_available() else "cpu"


def resolve_device(name: str) -> torch.device:
    """The torch device of ``--device NAME``: ``cpu``, ``cuda`` or ``cuda:N`` (the N-th GPU), checked to exist.

    Raises:
        ValueError: another name, or a CUDA device torch does not see (the message names ``--device``).
    """
    kind, colon, index = name.partition(":")
    if kind not in ("cpu", "cuda") or (colon and (kind == "cpu" or not index.isdigit())):
        raise ValueError(f"--device {name}: not a device warpavatar runs on; give cpu, cuda or cuda:N (the N-th GPU)")
    if kind == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if count == 0:
            raise ValueError(f"--device {name}: torch sees no CUDA device on this machine; give --device cpu")
        if colon and int(index) >= count:
            raise ValueError(f"--device {name}: torch sees {count} CUDA device{'s' if count > 1 else ''} "
                             f"(cuda:0 to cuda:{count - 1})")
    return torch.device(name)


@contextlib.contextmanager
def cpu_torch_settings(device: torch.device):
    """While active, on the CPU: one torch thread (unless ``OMP_NUM_THREADS`` says otherwise) and denormal
    floats flushed to zero; both restored on exit. Elsewhere it does nothing.

    A fit's heavy work on the CPU is Warp's kernels, which run on one core; torch's share is many small
    operations, which a second thread hardly speeds up and which, on a machine whose cores are busy, cost
    several times more CPU with two threads (OpenMP's waits). Adam's second moments of rarely seen Gaussians
    decay into denormals, which the CPU handles far slower than normal floats (BENCHMARKS.md, issue 18).
    """
    if device.type != "cpu":
        yield
        return
    threads = torch.get_num_threads()
    flush = torch.set_flush_denormal(True)
    if "OMP_NUM_THREADS" not in os.environ:
        torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)
        if flush:
            torch.set_flush_denormal(False)


class ArgumentParser(argparse.ArgumentParser):
    """An argparse parser whose usage errors are one line (the option and the problem), exit status 2, and
    that refuses path arguments which are not valid UTF-8 (OpenCV and USD crash or fail on them)."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (--help explains every option)\n")

    def parse_known_args(self, args=None, namespace=None):
        namespace, extras = super().parse_known_args(args, namespace)
        for action in self._actions:
            value = getattr(namespace, action.dest, None) if action.dest != argparse.SUPPRESS else None
            for item in value if isinstance(value, (list, tuple)) else (value,):
                if isinstance(item, os.PathLike) and not _is_utf8(os.fspath(item)):
                    option = action.option_strings[0] if action.option_strings else action.dest
                    self.error(f"{option} {shown_path(item)}: the path is not valid UTF-8, which OpenCV and USD "
                               "need; rename the file or folder")
        return namespace, extras


def _is_utf8(text: str) -> bool:
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        return False
    return True


def positive_number(text: str) -> float:
    """An argparse type: a finite number > 0."""
    value = float(text)
    if not (math.isfinite(value) and value > 0):
        raise ValueError(text)
    return value


positive_number.__name__ = "positive number"  # argparse's message: "invalid positive number value: '0'"


def check_output_path(path: Path, flag: str, *, folder: bool) -> None:
    """Refuse, before any work, an output that cannot be written: one below a file, or a folder where a file
    is to be written (``folder`` False) or a file where a folder is (``folder`` True); and one that is the working
    directory, an ancestor of it or the home folder (:func:`~warpavatar.io.output_files.check_output_location`)."""
    from warpavatar.io.output_files import check_output_location

    check_output_location(path, flag)
    for parent in path.parents:
        if parent.exists() and not parent.is_dir():
            raise ValueError(f"{flag} {path}: lies below {parent}, which is a file; the output cannot be written")
    if path.exists() and path.is_dir() != folder:
        wanted, found = ("folder", "file") if folder else ("file", "folder")
        raise ValueError(f"{flag} {path}: is a {found}; the output must be a {wanted}")


@contextlib.contextmanager
def one_line_warnings():
    """While active, a warning prints as one line, ``warning: <message>``, without the source line and path
    that Python's default format adds; the previous printer is restored on exit."""
    previous = warnings.showwarning

    def show(message, category, filename, lineno, file=None, line=None):
        text = " ".join(str(message).split())
        print(f"warning: {text}", file=sys.stderr if file is None else file)

    warnings.showwarning = show
    try:
        yield
    finally:
        warnings.showwarning = previous


def friendly_errors(main):
    """Report input errors (bad files, bad values, files that cannot be written) as one line on stderr with exit
    status 2, no traceback; end on Ctrl-C, SIGTERM or SIGHUP (:func:`termination_interrupts`) with one line and
    exit status 128 + the signal's number."""

    @functools.wraps(main)
    def wrapper(argv=None):
        try:
            with termination_interrupts(), one_line_warnings():
                return main(argv)
        except (ValueError, OSError) as error:
            text = " ".join(str(error).split())  # one line, whatever the message held
            print(f"error: {text}", file=sys.stderr)
            return 2
        except KeyboardInterrupt as interruption:
            number = interruption_signal(interruption)
            print(f"interrupted by {signal.Signals(number).name}", file=sys.stderr)
            return interruption_exit_status(number)

    return wrapper


def avatar_parser(prog: str, description: str, *, motion: bool, motion_default: str | None = None
                  ) -> argparse.ArgumentParser:
    """The parser of a command that loads a fitted avatar (positional, ``--device``, ``--no-progress``) and, with
    ``motion``, drives it with a motion (:func:`add_motion_arguments`; ``motion_default``: see there)."""
    parser = ArgumentParser(prog=prog, description=description, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_avatar_arguments(parser)
    if motion:
        add_motion_arguments(parser, default=motion_default)
    return parser


def add_avatar_arguments(parser: argparse.ArgumentParser) -> None:
    """The fitted avatar to load (positional), ``--device`` and ``--no-progress``."""
    parser.add_argument("avatar", type=Path, help="the fit's output folder (or its avatar.pt)")
    parser.add_argument("--device", default=default_device(), help="torch device: cpu or cuda (default: %(default)s)")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")


TRAINING_MOTION_HELP = "the fit's training motion: training_poses.npz in the fit's output folder"
"""What ``--motion`` defaults to, as its help says it."""


def add_motion_arguments(parser: argparse.ArgumentParser, *, default: str | None = None) -> None:
    """The motion that drives an avatar: ``--motion`` and how to read and cut it. ``default``: what the command
    does without ``--motion``, for its help (None: :data:`TRAINING_MOTION_HELP`, what :func:`load_motion_for`
    reads)."""
    parser.add_argument("--motion", type=Path, default=None,
                        help="motion source: a video folder (its poses.npz), a poses .npz with bone_transforms of "
                             f"the same skeleton, or a .bvh file (default: {default or TRAINING_MOTION_HELP})")
    parser.add_argument("--frames", default=None, metavar="A:B", help="only motion frames A..B-1 (default: all)")
    parser.add_argument("--fps", type=positive_number, default=None,
                        help="frames per second of the output (default: the motion's)")
    parser.add_argument("--name-map", type=Path, default=None,
                        help="BVH only: JSON file mapping avatar joint names to BVH joint names "
                             "(default: same names, case-insensitive); unmapped joints keep their rest pose")
    parser.add_argument("--bvh-scale", type=positive_number, default=None,
                        help="BVH only: metres per BVH unit (default: from the ratio of skeleton heights)")
    parser.add_argument("--bvh-up", choices=("X", "Y", "Z"), default=None, help="BVH only: its up axis (default Y)")
    parser.add_argument("--grown-rotations", type=Path, default=None, metavar="FILE",
                        help="explicit rotations of the joints grown by --grow-joints, one row per motion frame: a "
                             ".npy [T, E, 4] or a .npz with a 'rotations' array, (w, x, y, z) in each grown joint's "
                             "parent rest frame (default: training instants replay their learned rotations, other "
                             "poses keep the grown joints at rest)")


def load_avatar(args):
    """The avatar ``args.avatar`` on ``args.device``."""
    from warpavatar.model import Avatar

    return Avatar.load(args.avatar, device=resolve_device(args.device))


def training_motion_path(avatar_path: Path) -> Path:
    """The training motion a fit wrote beside its avatar: ``training_poses.npz`` in the output folder
    ``avatar_path`` (or in the folder of the avatar file ``avatar_path``)."""
    from warpavatar.fit.outputs import TRAINING_MOTION_NAME

    folder = avatar_path if avatar_path.is_dir() else avatar_path.parent
    return folder / TRAINING_MOTION_NAME


def load_motion_for(avatar, args):
    """The motion of ``args`` retargeted to ``avatar``, its frame slice, and the explicit per-frame inputs of the
    avatar's parts it names (``{part name: [T, ...]}``: the grown joints' rotations).

    Without ``--motion`` (``args.motion`` None) it reads the fit's training motion (:func:`training_motion_path`
    of ``args.avatar``) and sets ``args.motion`` to it.

    Raises:
        ValueError: no ``--motion`` and no training motion beside the avatar (the message names the file).
    """
    import json

    from warpavatar.extensions.joint_growth import ExtraJoints
    from warpavatar.io.animation import parse_frame_range, read_grown_rotations
    from warpavatar.io.motion import load_motion

    if args.motion is None:
        path = training_motion_path(args.avatar)
        if not path.is_file():
            raise ValueError(f"{path}: no such file, so there is no training motion to default to (fits write it; "
                             "older ones did not); give --motion")
        args.motion = path
    name_map = None
    if args.name_map is not None:
        try:
            name_map = json.loads(args.name_map.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
            raise ValueError(f"--name-map {args.name_map}: cannot be read as JSON ({error})") from None
        if not isinstance(name_map, dict) or not all(isinstance(key, str) and isinstance(value, str)
                                                     for key, value in name_map.items()):
            raise ValueError(f"--name-map {args.name_map}: must be a JSON object of avatar joint name -> BVH "
                             "joint name (strings)")
    frames = parse_frame_range(args.frames)
    motion = load_motion(args.motion, avatar.skeleton, name_map=name_map, frames=frames,
                         bvh_scale=args.bvh_scale, bvh_up=args.bvh_up)
    if motion.undriven_joints:
        print(f"note: {len(motion.undriven_joints)} avatar joints have no joint in {args.motion} and keep their rest "
              f"pose relative to their parent: {', '.join(motion.undriven_joints[:8])}"
              f"{' ...' if len(motion.undriven_joints) > 8 else ''} (--name-map maps them)")
    part_inputs = {}
    if args.grown_rotations is not None:
        part_inputs[ExtraJoints.name] = read_grown_rotations(
            args.grown_rotations, frame_count=motion.bone_transforms.shape[0], joint_count=avatar.grown_joint_count)
    return motion, frames, part_inputs
