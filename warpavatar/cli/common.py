"""Pieces shared by the command-line tools: device choice, the avatar and motion options, and turning expected
errors into clear messages."""

from __future__ import annotations

import argparse
import contextlib
import functools
import math
import os
import sys
from pathlib import Path

import torch

__all__ = ["default_device", "resolve_device", "cpu_torch_settings", "ArgumentParser", "positive_number",
           "check_output_path", "friendly_errors", "avatar_parser", "load_avatar", "load_motion_for"]


def default_device() -> str:
    return "cuda" if torch.cuda.is_available() else "cpu"


def resolve_device(name: str) -> torch.device:
    device = torch.device(name)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise SystemExit("error: --device cuda was asked for but torch sees no CUDA device")
    return device


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
    """An argparse parser whose usage errors are one line (the option and the problem), exit status 2."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (--help explains every option)\n")


def positive_number(text: str) -> float:
    """An argparse type: a finite number > 0."""
    value = float(text)
    if not (math.isfinite(value) and value > 0):
        raise ValueError(text)
    return value


positive_number.__name__ = "positive number"  # argparse's message: "invalid positive number value: '0'"


def check_output_path(path: Path, flag: str, *, folder: bool) -> None:
    """Refuse, before any work, an output that cannot be written: one below a file, or a folder where a file
    is to be written (``folder`` False) or a file where a folder is (``folder`` True)."""
    for parent in path.parents:
        if parent.exists() and not parent.is_dir():
            raise ValueError(f"{flag} {path}: lies below {parent}, which is a file; the output cannot be written")
    if path.exists() and path.is_dir() != folder:
        wanted, found = ("folder", "file") if folder else ("file", "folder")
        raise ValueError(f"{flag} {path}: is a {found}; the output must be a {wanted}")


def friendly_errors(main):
    """Report input errors (bad files, bad values, files that cannot be written) as one line on stderr with exit
    status 2, no traceback."""

    @functools.wraps(main)
    def wrapper(argv=None):
        try:
            return main(argv)
        except (ValueError, OSError) as error:
            text = " ".join(str(error).split())  # one line, whatever the message held
            print(f"error: {text}", file=sys.stderr)
            return 2
        except KeyboardInterrupt:
            print("interrupted", file=sys.stderr)
            return 130

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


def add_motion_arguments(parser: argparse.ArgumentParser, *, default: str | None = None) -> None:
    """The motion that drives an avatar: ``--motion`` and how to read and cut it. ``default``: what the command
    does without ``--motion``, for its help (None: ``--motion`` is required)."""
    parser.add_argument("--motion", required=default is None, type=Path, default=None,
                        help="motion source: a video folder (its poses.npz), a poses .npz with bone_transforms of "
                             "the same skeleton, or a .bvh file" + (f" (default: {default})" if default else ""))
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


def load_motion_for(avatar, args):
    """The motion of ``args`` retargeted to ``avatar``, its frame slice, and the explicit per-frame inputs of the
    avatar's parts it names (``{part name: [T, ...]}``: the grown joints' rotations)."""
    import json

    from warpavatar.extensions.joint_growth import ExtraJoints
    from warpavatar.io.animation import parse_frame_range, read_grown_rotations
    from warpavatar.io.motion import load_motion

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
