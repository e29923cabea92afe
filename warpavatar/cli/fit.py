"""``warpavatar-fit``: fit an animatable Gaussian avatar to a video folder."""

from __future__ import annotations

import argparse
import contextlib
import shlex
import shutil
import signal
import sys
import threading
import time
from pathlib import Path

from warpavatar.cli.common import (ArgumentParser, check_output_path, cpu_torch_settings, default_device,
                                   friendly_errors, resolve_device)
from warpavatar.fit.arguments import add_config_arguments, config_from_arguments
from warpavatar.fit.presets import preset_names

DESCRIPTION = """Fit an animatable 3D Gaussian avatar to a video folder (see docs/data.md for the format).

Outputs in the output folder: avatar.pt (the avatar: Gaussians, skinning field, skeleton, its optional parts,
config; loads back with warpavatar.model.Avatar.load), canonical.ply (the canonical Gaussians with the 3DGS
attribute names), config.json, train_log.jsonl (one JSON line per logged step: every loss term by name),
training_poses.npz (the poses fitted on, as a poses.npz: warpavatar-view plays it), checkpoint.pt (to resume)
and previews/ (render | ground truth for a few training frames).
A non-empty output folder is refused unless --resume continues its fit or --overwrite starts over in it.
Ctrl-C stops after the step under way, writes checkpoint.pt and prints the command that resumes (exit
status 130); bad input is one line on stderr with exit status 2.

Options: the main ones first, then the core's groups, then one group per optional part (extension) with its
research knobs. Each overrides the preset's value; --help shows the default and where a preset differs.
"""


FIT_OUTPUTS = ("avatar.pt", "canonical.ply", "config.json", "train_log.jsonl", "checkpoint.pt", "previews",
               "demo_eval.json", "poses_refined.npz", "training_poses.npz")
"""What a fit writes in its output folder (``--overwrite`` deletes these)."""


def build_parser() -> argparse.ArgumentParser:
    parser = ArgumentParser(prog="warpavatar-fit", description=DESCRIPTION,
                            formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("video_folder", nargs="?", type=Path,
                        help="the video folder to fit (or a subject folder holding train/); omit with --demo")
    parser.add_argument("-o", "--output", type=Path, default=None,
                        help="output folder (default: ./warpavatar-out/<folder name>)")
    parser.add_argument("--resume", action="store_true",
                        help="continue from checkpoint.pt in the output folder (same options required; "
                             "without a checkpoint the fit starts from the beginning)")
    parser.add_argument("--overwrite", action="store_true",
                        help="start a new fit in a non-empty output folder, deleting the earlier fit's outputs "
                             f"there ({', '.join(FIT_OUTPUTS)}); other files stay (default: refuse a non-empty "
                             "folder)")
    parser.add_argument("--demo", action="store_true",
                        help="fit the small built-in demo subject (a reduced robot) with the 'demo' preset (about 3 "
                             "minutes on 2 CPU cores) and evaluate it on its held-out view and pose")
    add_fit_options(parser)
    return parser


def add_fit_options(parser: argparse.ArgumentParser, *, device_help: str | None = None) -> None:
    """The options of one fit, shared with ``warpavatar-fit-many``: ``--preset``, ``--device``, ``--no-progress``
    and one flag per configuration field. With ``device_help``, ``--device`` defaults to None (the caller
    chooses) and is explained by that text."""
    parser.add_argument("--preset", choices=preset_names(), default=None,
                        help="named configuration: 'default' (quality, GPU), 'quick' (small, CPU, minutes) or "
                             "'demo' (quick shortened for the built-in demo); default: 'default' on CUDA, 'quick' "
                             "on CPU, 'demo' with warpavatar-fit --demo")
    parser.add_argument("--device", default=None if device_help else default_device(),
                        help=device_help or "torch device: cpu or cuda (default: %(default)s)")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    parser.add_argument("--cuda-graph", choices=("auto", "on", "off"), default="auto",
                        help="capture the steady training step (between densification rounds) as a CUDA graph and "
                             "replay it: 'auto' on CUDA devices (a capture that fails turns it off with a warning), "
                             "'on' (CUDA required, a failed capture is an error), 'off'; the fit is the same up to "
                             "the rounding of atomic additions, only faster (default: %(default)s)")
    add_config_arguments(parser)


@friendly_errors
def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    device = resolve_device(args.device)
    with cpu_torch_settings(device):
        return fit_and_report(args, device, argv)


def fit_and_report(args: argparse.Namespace, device, argv) -> int:
    """The fit of ``main``'s parsed arguments on ``device`` (and the demo's evaluation); its exit status."""
    from warpavatar import data
    from warpavatar.evaluate import evaluate_held_out, write_json_atomic
    from warpavatar.fit import Trainer

    preset_name = args.preset or ("demo" if args.demo else "default" if device.type == "cuda" else "quick")
    config = config_from_arguments(args, preset_name)
    if args.demo:
        subject_root = data.demo_subject_path()
        folder = subject_root / "train"
    elif args.video_folder is None:
        raise ValueError("give a video folder to fit, or --demo")
    else:
        folder = args.video_folder
        subject_root = folder if (folder / "train").is_dir() else None
        if subject_root is not None:
            folder = folder / "train"
    output = args.output or Path("warpavatar-out") / ((subject_root or folder).name if not args.demo else "demo")
    check_output_folder(output, resume=args.resume, overwrite=args.overwrite)
    video = data.load_video_folder(folder, scale=config.image_scale)
    print(f"fitting {folder} ({video.frame_count} frames, {video.width}x{video.height}, "
          f"{video.skeleton.joint_count} joints) on {device} with preset '{preset_name}' -> {output}")
    if args.overwrite:
        remove_fit_outputs(output)
    start = time.time()
    trainer = Trainer(video, config, output, device=device, cuda_graph=args.cuda_graph)
    if args.resume and not (output / "checkpoint.pt").is_file():
        print(f"no checkpoint.pt in {output}: the fit starts from the beginning")
    with stop_on_interrupt(trainer):
        trainer.fit(resume=args.resume, progress=not args.no_progress)
    if trainer.stopped_early:
        print(f"interrupted at step {trainer.step} of {config.iterations}: checkpoint written to "
              f"{output / 'checkpoint.pt'}; resume with: {resume_command(argv)}", file=sys.stderr)
        return 130
    minutes = (time.time() - start) / 60
    print(f"done in {minutes:.1f} min: {trainer.gaussians.count} Gaussians; avatar at {output / 'avatar.pt'}")
    for line in trainer.summary_lines():
        print(line)
    if args.demo:
        results = evaluate_held_out(trainer.avatar, data.load_subject(subject_root), progress=False)
        for label, result in results.items():
            print(f"  {label}: masked PSNR {result['psnr_masked']:.2f} dB, "
                  f"full-frame PSNR {result['psnr']:.2f} dB, SSIM {result['ssim']:.4f}")
        write_json_atomic(output / "demo_eval.json", results)
        print(f"demo result in {output.resolve()} (avatar.pt, canonical.ply, previews/, demo_eval.json)")
    return 0


# --------------------------------------------------------------------------------------------------------
# The output folder and interruptions


def check_output_folder(output: Path, *, resume: bool, overwrite: bool) -> None:
    """Refuse, before any work, an output path that cannot be a folder (a file, or below a file) and a
    non-empty folder that neither ``--resume`` nor ``--overwrite`` allows."""
    if resume and overwrite:
        raise ValueError("--resume and --overwrite contradict each other: give one")
    check_output_path(output, "-o", folder=True)
    if output.is_dir() and not resume and not overwrite:
        entries = sorted(entry.name for entry in output.iterdir())
        if entries:
            shown = ", ".join(entries[:4]) + (f" and {len(entries) - 4} more" if len(entries) > 4 else "")
            raise ValueError(f"-o {output}: the folder is not empty ({shown}); give --resume to continue its fit, "
                             "--overwrite to start over in it, or another -o")


def remove_fit_outputs(output: Path) -> None:
    """Delete what an earlier fit wrote in ``output`` (:data:`FIT_OUTPUTS` and their temporary files)."""
    for name in FIT_OUTPUTS:
        for path in (output / name, output / f"{name}.tmp"):
            if path.is_dir() and not path.is_symlink():
                shutil.rmtree(path)
            elif path.exists() or path.is_symlink():
                path.unlink()


@contextlib.contextmanager
def stop_on_interrupt(trainer):
    """While active, the first SIGINT (Ctrl-C) asks ``trainer`` to stop after its current step (it then writes
    a checkpoint); a second one interrupts at once. Signals are only handled on the main thread."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handle(signum, frame):
        trainer.request_stop()
        signal.signal(signal.SIGINT, signal.default_int_handler)

    previous = signal.signal(signal.SIGINT, handle)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def resume_command(argv) -> str:
    """The command line that resumes the fit of ``argv`` (its options with --resume, without --overwrite)."""
    arguments = [argument for argument in (sys.argv[1:] if argv is None else argv) if argument != "--overwrite"]
    if "--resume" not in arguments:
        arguments.append("--resume")
    return shlex.join(["warpavatar-fit", *arguments])


if __name__ == "__main__":
    sys.exit(main())
