"""``warpavatar-fit``: fit an animatable Gaussian avatar to a video folder."""

from __future__ import annotations

import argparse
import contextlib
import shlex
import shutil
import signal
import sys
import time
from pathlib import Path

from warpavatar.cli.common import (ArgumentParser, check_output_path, cpu_torch_settings, default_device,
                                   friendly_errors, interruption_exit_status, resolve_device, stop_on_signals)
from warpavatar.fit.arguments import (MAIN_GROUP, add_config_arguments, add_help_options, config_from_arguments,
                                    main_option, schedule_warning)
from warpavatar.fit.presets import preset_names
from warpavatar.io.output_files import (OUTPUT_MARKER_NAME, mark_output_folder, output_lock, read_output_marker,
                                        remove_leftover_temporaries)

DESCRIPTION = """Fit an animatable 3D Gaussian avatar to a video folder (see docs/data.md for the format).

Outputs in the output folder: avatar.pt (the avatar: Gaussians, skinning field, skeleton, its optional parts,
config; loads back with warpavatar.model.Avatar.load), canonical.ply (the canonical Gaussians with the 3DGS
attribute names), config.json, train_log.jsonl (one JSON line per logged step: every loss term by name),
training_poses.npz (the poses fitted on, as a poses.npz: warpavatar-view plays it), checkpoint.pt (to resume)
and previews/ (render | ground truth for a few training frames).
A non-empty output folder is refused unless --resume continues its fit or --overwrite starts over in it; a
folder holding another warpavatar output (its .warpavatar-output marker says which) is always refused. One fit at
a time writes an output folder: a second one is refused while the first runs.
Ctrl-C, SIGTERM (a scheduler's or container's stop) and SIGHUP (a logout) stop after the step under way, write
checkpoint.pt and print the command that resumes (exit status 130, 143 and 129); a second one stops at once.
Bad input is one line on stderr with exit status 2.

Options (--help shows the main ones, --help-all all of them): the main ones first, then the core's groups, then
one group per optional part (extension) with its research knobs; the groups of experimental parts say so. Each
overrides the preset's value, and its help gives its unit, its default and where a preset differs.
"""


FIT_OUTPUTS = ("avatar.pt", "canonical.ply", "config.json", "train_log.jsonl", "checkpoint.pt", "previews",
               "demo_eval.json", "poses_refined.npz", "training_poses.npz")
"""What a fit writes in its output folder (``--overwrite`` deletes these; the folder's marker stays)."""

FIT_KIND = "fit"
"""The kind of output the marker of a fit's folder names."""


SUMMARY = """Fit an animatable 3D Gaussian avatar to a video folder (docs/data.md). The
output folder gets avatar.pt, canonical.ply, config.json, previews/ and a
checkpoint; Ctrl-C stops with a checkpoint that --resume continues. Bad input
is one line on stderr, exit status 2."""

EXAMPLES = (("warpavatar-fit --demo", "the built-in demo subject: about 3 minutes on 2 CPU cores, then evaluated"),
            ("warpavatar-fit path/to/subject -o out/subject --device cuda", "a subject (its train/) or a video folder"))
"""The ``(command, comment)`` pairs ``warpavatar-fit --help`` ends with."""


def build_parser() -> argparse.ArgumentParser:
    """The ``warpavatar-fit`` parser: ``--help`` shows the main options and :data:`EXAMPLES`, ``--help-all``
    every option by group."""
    parser = ArgumentParser(prog="warpavatar-fit", description=DESCRIPTION, add_help=False,
                            usage="%(prog)s [VIDEO_FOLDER] [-o OUTPUT] [--demo] [options]",
                            formatter_class=argparse.RawDescriptionHelpFormatter)
    main = parser.add_argument_group(MAIN_GROUP)
    main_option(main.add_argument("video_folder", nargs="?", type=Path,
                                  help="the video folder to fit (or a subject folder holding train/); omit with "
                                       "--demo (default: none)"))
    main_option(main.add_argument("-o", "--output", type=Path, default=None,
                                  help="output folder (default: ./warpavatar-out/<folder name>)"))
    main_option(main.add_argument("--demo", action="store_true",
                                  help="fit the built-in demo subject (a reduced robot) with the 'demo' preset and "
                                       "evaluate it on its held-out view and pose (default: off)"))
    main_option(main.add_argument("--resume", action="store_true",
                                  help="continue from checkpoint.pt in the output folder: the same video folder, "
                                       "skeleton and options are required (default: off)"))
    main_option(main.add_argument("--overwrite", action="store_true",
                                  help="start over in a non-empty output folder, deleting the earlier fit's "
                                       "outputs; other files stay (default: off, a non-empty folder is refused)"))
    add_fit_options(parser, main)
    add_help_options(main, summary=SUMMARY, examples=EXAMPLES)
    return parser


def add_fit_options(parser: argparse.ArgumentParser, main, *, device_help: str | None = None) -> None:
    """The options of one fit, shared with ``warpavatar-fit-many``: ``--preset``, ``--device``, ``--no-progress``
    and the main configuration flags (:data:`~warpavatar.fit.arguments.HELP_OPTIONS`) into ``main`` (the main
    options' group), marked for ``--help``; ``--cuda-graph`` and every other configuration flag in groups of their
    own. With ``device_help``, ``--device`` defaults to None (the caller chooses) and is explained by that text."""
    main_option(main.add_argument("--preset", choices=preset_names(), default=None, metavar="NAME",
                                  help="named configuration: 'default' (quality, GPU), 'quick' (small, CPU, "
                                       "minutes) or 'demo' (quick shortened for the demo) (default: 'default' on "
                                       "CUDA, else 'quick'; 'demo' with warpavatar-fit --demo)"))
    main_option(main.add_argument("--device", default=None if device_help else default_device(),
                                  help=device_help or "torch device: cpu, cuda or cuda:N (default: %(default)s, "
                                                      "cuda where torch sees a GPU)"))
    running = parser.add_argument_group("running the fit")
    running.add_argument("--cuda-graph", choices=("auto", "on", "off"), default="auto",
                         help="capture the steady training step (between densification rounds) as a CUDA graph and "
                              "replay it: 'auto' on CUDA devices (a capture that fails turns it off with a warning), "
                              "'on' (CUDA required, a failed capture is an error), 'off'; the fit is the same up to "
                              "the rounding of atomic additions, only faster (default: %(default)s)")
    add_config_arguments(parser, main=main)
    main_option(main.add_argument("--no-progress", action="store_true",
                                  help="hide the progress bar (default: shown)"))


@friendly_errors
def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    device = resolve_device(args.device)
    output = fit_paths(args)[2]
    check_output_path(output, "-o", folder=True)
    with cpu_torch_settings(device), output_lock(output, flag="-o"):
        return fit_and_report(args, device, argv)


def fit_paths(args: argparse.Namespace) -> tuple[Path | None, Path, Path]:
    """``(subject folder or None, the video folder to fit, the output folder)`` of ``main``'s parsed arguments."""
    from warpavatar import data

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
    return subject_root, folder, output


def fit_and_report(args: argparse.Namespace, device, argv) -> int:
    """The fit of ``main``'s parsed arguments on ``device`` (and the demo's evaluation); its exit status."""
    from warpavatar.evaluate import evaluate_held_out, score_line, write_json_atomic
    from warpavatar.fit import Trainer, load_training_video
    from warpavatar.fit.checkpoint import CHECKPOINT_NAME, check_resume, read_checkpoint

    preset_name = args.preset or ("demo" if args.demo else "default" if device.type == "cuda" else "quick")
    config = config_from_arguments(args, preset_name)
    subject_root, folder, output = fit_paths(args)
    check_output_folder(output, resume=args.resume, overwrite=args.overwrite)
    video = load_training_video(folder, config)
    if args.resume and (output / CHECKPOINT_NAME).is_file():  # refused before any work when it cannot be continued
        check_resume(output / CHECKPOINT_NAME, read_checkpoint(output / CHECKPOINT_NAME, mmap=True), config=config,
                     video=video)
    print(f"fitting {folder} ({video.frame_count} frames, {video.width}x{video.height}, "
          f"{video.skeleton.joint_count} joints) on {device} with preset '{preset_name}' -> {output}")
    if args.overwrite:
        remove_fit_outputs(output)
    else:  # the lock is held: temporary files there are a killed fit's
        remove_leftover_temporaries(output, FIT_OUTPUTS)
    mark_output_folder(output, FIT_KIND)
    start = time.time()
    trainer = Trainer(video, config, output, device=device, cuda_graph=args.cuda_graph)
    # after the trainer, whose parts check their own options first; a resumed fit said it at its start
    warning = schedule_warning(config)
    if warning is not None and not (args.resume and (output / "checkpoint.pt").is_file()):
        print(warning, file=sys.stderr)
    if args.resume and not (output / "checkpoint.pt").is_file():
        print(f"no checkpoint.pt in {output}: the fit starts from the beginning")
    with stop_on_interrupt(trainer) as stop:
        trainer.fit(resume=args.resume, progress=not args.no_progress)
    if trainer.stopped_early:
        number = stop.signal_number or signal.SIGINT
        print(f"interrupted by {signal.Signals(number).name} at step {trainer.step} of {config.iterations}: "
              f"checkpoint written to {output / 'checkpoint.pt'}; resume with: {resume_command(argv)}",
              file=sys.stderr)
        return interruption_exit_status(number)
    minutes = (time.time() - start) / 60
    print(f"done in {minutes:.1f} min: {trainer.gaussians.count} Gaussians; avatar at {output / 'avatar.pt'}")
    for line in trainer.summary_lines():
        print(line)
    if args.demo:  # scored at the fit's training resolution, as warpavatar-fit-many --eval scores
        results = evaluate_held_out(trainer.avatar, subject_root, image_scale=config.image_scale, progress=False)
        for label, result in results.items():
            print(f"  {score_line(label, result)}")
        write_json_atomic(output / "demo_eval.json", results)
        print(f"demo result in {output.resolve()} (avatar.pt, canonical.ply, previews/, demo_eval.json)")
    print(next_commands(output))
    return 0


def next_commands(output: Path) -> str:
    """The line a finished fit ends with: the commands that look at, render and export the avatar in
    ``output`` (each drives it with the fit's training motion by default)."""
    folder = shlex.quote(str(output))
    return (f"next: warpavatar-view {folder} | warpavatar-render {folder} --orbit -o turntable.mp4 | "
            f"warpavatar-animate {folder} -o avatar.usdc")


# --------------------------------------------------------------------------------------------------------
# The output folder and interruptions


def check_output_folder(output: Path, *, resume: bool, overwrite: bool) -> None:
    """Refuse, before any work, an output path that cannot be a folder (a file, or below a file), a folder whose
    marker names another kind of warpavatar output, and a non-empty folder that neither ``--resume`` nor
    ``--overwrite`` allows."""
    if resume and overwrite:
        raise ValueError("--resume and --overwrite contradict each other: give one")
    check_output_path(output, "-o", folder=True)
    marker = read_output_marker(output) if output.is_dir() else None
    if marker is not None and marker[0] != FIT_KIND:
        raise ValueError(f"-o {output}: holds a warpavatar {marker[0]} output, not a fit; choose another -o")
    if output.is_dir() and not resume and not overwrite:
        entries = sorted(entry.name for entry in output.iterdir() if entry.name != OUTPUT_MARKER_NAME)
        if entries:
            shown = ", ".join(entries[:4]) + (f" and {len(entries) - 4} more" if len(entries) > 4 else "")
            raise ValueError(f"-o {output}: the folder is not empty ({shown}); give --resume to continue its fit, "
                             "--overwrite to start over in it, or another -o")


def remove_fit_outputs(output: Path) -> None:
    """Delete what an earlier fit wrote in ``output``: :data:`FIT_OUTPUTS` and the temporary files of theirs an
    interrupted fit left (their own names, :func:`~warpavatar.io.output_files.temporary_path`); nothing else."""
    remove_leftover_temporaries(output, FIT_OUTPUTS)
    for name in FIT_OUTPUTS:
        path = output / name
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        elif path.exists() or path.is_symlink():
            path.unlink()


@contextlib.contextmanager
def stop_on_interrupt(trainer, *, even_ignored: bool = False):
    """While active, the first of SIGINT (Ctrl-C), SIGTERM or SIGHUP asks ``trainer`` to stop after its current
    step (it then writes a checkpoint) and is recorded in the yielded
    :class:`~warpavatar.cli.common.StopRequest`; a second one raises :class:`~warpavatar.cli.common.Interrupted`
    at once (:func:`~warpavatar.cli.common.stop_on_signals`, whose ``even_ignored`` this passes on)."""
    with stop_on_signals(trainer.request_stop, even_ignored=even_ignored) as stop:
        yield stop


def resume_command(argv) -> str:
    """The command line that resumes the fit of ``argv`` (its options with --resume, without --overwrite)."""
    arguments = [argument for argument in (sys.argv[1:] if argv is None else argv) if argument != "--overwrite"]
    if "--resume" not in arguments:
        arguments.append("--resume")
    return shlex.join(["warpavatar-fit", *arguments])


if __name__ == "__main__":
    sys.exit(main())
