"""``warpavatar-fit-many``: fit many subjects, one Ray task per subject, on this machine or a Ray cluster."""

from __future__ import annotations

import argparse
import os
import signal
import sys
from pathlib import Path

from warpavatar.cli.common import (ArgumentParser, check_output_path, friendly_errors, interruption_exit_status,
                                   interruption_signal, stop_on_signals)
from warpavatar.cli.fit import add_fit_options
from warpavatar.fit.arguments import MAIN_GROUP, add_help_options, main_option

DESCRIPTION = """Fit every subject of a batch, one Ray task per subject (see docs/cluster.md).

Each SUBJECT is a subject folder (holding train/, and novel_view/*, novel_pose/* for --eval) or a video folder,
or a text file listing such folders one a line (relative to the file's folder; # starts a comment). A subject is
named by its folder's name; its outputs (those of warpavatar-fit, and fit-many.json: the done marker) go to
OUT_ROOT/<name>/. The summary (subject, status, attempts, fit time, Gaussians, held-out metrics) is printed at
the end and written to OUT_ROOT/fit-many-summary.json and .csv.

Without --ray-address a local Ray instance starts on this machine; --ray-address auto or HOST:PORT joins a running
cluster (every node must see the subject folders and OUT_ROOT at the same paths). A task whose worker dies is run
again (--max-retries) and continues from the subject's last checkpoint; a subject whose input is invalid fails
alone; subjects finished by an earlier run with the same options are skipped unless --force (with other options
they fail, saying which). Ctrl-C, SIGTERM or SIGHUP stop the running fits after their step under way, each
writing its checkpoint, and the same command continues them. Exit status: 0 when every subject is done or
skipped, 1 when one failed, 2 for a bad option or subject list, 130/143/129 when interrupted by
SIGINT/SIGTERM/SIGHUP. Needs Ray: pip install -e ".[cluster]".

Every warpavatar-fit option applies to every fit (see warpavatar-fit --help).
"""

SUMMARY = """Fit every subject of a batch, one Ray task per subject (docs/cluster.md). Each
fit's outputs go to OUT_ROOT/<subject name>/, the summary to
OUT_ROOT/fit-many-summary.json and .csv. Every warpavatar-fit option applies to
every fit. Needs Ray: pip install -e ".[cluster]"."""

EXAMPLES = (("warpavatar-fit-many subjects.txt -o out --eval --gpus-per-fit 0.5",
             "the subjects listed in subjects.txt, two fits a GPU, then evaluated"),
            ("warpavatar-fit-many data/a data/b -o out --ray-address auto --preset quick",
             "two subject folders on the running Ray cluster this node belongs to"))
"""The ``(command, comment)`` pairs ``warpavatar-fit-many --help`` ends with."""

#: test hook: ``SUBJECT:STEP`` kills the first attempt of that subject's task after STEP steps (SIGKILL)
TEST_KILL_VARIABLE = "WARPAVATAR_FIT_MANY_TEST_KILL"


def build_parser() -> argparse.ArgumentParser:
    """The ``warpavatar-fit-many`` parser: ``--help`` shows the main options and :data:`EXAMPLES`,
    ``--help-all`` every option by group (warpavatar-fit's included)."""
    parser = ArgumentParser(prog="warpavatar-fit-many", description=DESCRIPTION, add_help=False,
                            usage="%(prog)s SUBJECT [SUBJECT ...] -o OUT_ROOT [options]",
                            formatter_class=argparse.RawDescriptionHelpFormatter)
    main = parser.add_argument_group(MAIN_GROUP)
    main_option(main.add_argument("subjects", nargs="+", metavar="SUBJECT", type=Path,
                                  help="subject folder, video folder, or a text file listing them one a line "
                                       "(no default)"))
    main_option(main.add_argument("-o", "--output", required=True, type=Path, metavar="OUT_ROOT",
                                  help="output root: each subject's fit goes to OUT_ROOT/<subject name>/ (no "
                                       "default)"))
    batch = parser.add_argument_group("batch options")
    main_option(batch.add_argument(
        "--ray-address", default=None, metavar="ADDRESS",
        help="Ray cluster to join: 'auto' (the cluster this node belongs to) or HOST:PORT of its head (default: "
             "start a local Ray instance on this machine)"))
    main_option(batch.add_argument(
        "--gpus-per-fit", type=float, default=None, metavar="GPUS",
        help="GPUs each fit asks Ray for; a fraction shares a GPU between fits (0.5: two at a time) (default: 1 "
             "when the cluster has GPUs, else 0)"))
    main_option(batch.add_argument("--cpus-per-fit", type=float, default=1.0, metavar="CPUS",
                                   help="CPU cores each fit asks Ray for (default: %(default)s)"))
    main_option(batch.add_argument(
        "--max-retries", type=int, default=3, metavar="N",
        help="how many times a fit whose worker died (or hit a disk, network or GPU-memory error) is run again, "
             "continuing from its last checkpoint (default: %(default)s)"))
    batch.add_argument(
        "--kernel-cache", type=Path, default=None, metavar="DIR",
        help="Warp's kernel cache directory for every fit: the fits of a host share it and compile each kernel "
             "once (default: $WARP_CACHE_PATH where set, else Warp's per-user cache directory of each node)")
    main_option(batch.add_argument(
        "--force", action="store_true",
        help="fit again, from the start, subjects that an earlier run finished (default: off, skip them)"))
    main_option(batch.add_argument(
        "--eval", action="store_true",
        help="measure each avatar on its subject's novel_view/* and novel_pose/* folders at the fit's image scale "
             "(eval.json in its folder, means in the summary) (default: off)"))
    add_fit_options(parser, main, device_help="torch device of each fit: cpu or cuda, the GPU Ray gives the fit "
                                              "(default: cuda when fits get GPUs, see --gpus-per-fit, else cpu)")
    add_help_options(main, summary=SUMMARY, examples=EXAMPLES)
    return parser


def _test_kill() -> dict[str, int]:
    value = os.environ.get(TEST_KILL_VARIABLE)
    if not value:
        return {}
    name, _, step = value.rpartition(":")
    if not name or not step.isdigit():
        raise ValueError(f"{TEST_KILL_VARIABLE}={value!r}: expected SUBJECT:STEP")
    return {name: int(step)}


def _check_batch_options(args) -> None:
    if args.gpus_per_fit is not None and args.gpus_per_fit < 0:
        raise ValueError(f"--gpus-per-fit must be >= 0, got {args.gpus_per_fit}")
    if not args.cpus_per_fit > 0:
        raise ValueError(f"--cpus-per-fit must be positive, got {args.cpus_per_fit}")
    if args.max_retries < 0:
        raise ValueError(f"--max-retries must be >= 0, got {args.max_retries}")
    if args.device is not None and args.device not in ("cpu", "cuda"):
        raise ValueError(f"--device takes cpu or cuda (Ray chooses the GPU), got {args.device!r}")


@friendly_errors
def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    _check_batch_options(args)
    check_output_path(args.output, "-o", folder=True)
    if args.kernel_cache is not None:
        check_output_path(args.kernel_cache, "--kernel-cache", folder=True)
    kernel_cache = args.kernel_cache or os.environ.get("WARP_CACHE_PATH") or None
    from warpavatar.batch import read_subjects, run_batch, summary_lines, write_summary
    from warpavatar.batch.runner import cluster_gpu_count, connect_ray, import_ray
    from warpavatar.fit.arguments import config_from_arguments

    subjects = read_subjects(args.subjects)  # list files checked before Ray starts
    kill = _test_kill()
    try:
        ray = import_ray()
    except ModuleNotFoundError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    connected = connect_ray(args.ray_address)
    try:
        # the first stop signal asks the fits to stop at their next step, a second one interrupts (the handlers
        # are installed here, after ray.init, which replaced the SIGTERM handler with its own)
        with stop_on_signals() as stop:
            gpus = cluster_gpu_count()
            gpus_per_fit = args.gpus_per_fit if args.gpus_per_fit is not None else (1.0 if gpus > 0 else 0.0)
            if gpus_per_fit > gpus:
                raise ValueError(f"--gpus-per-fit {gpus_per_fit:g}: the Ray cluster has {gpus:g} GPUs "
                                 "(give --gpus-per-fit 0 to fit on CPUs)")
            device = args.device or ("cuda" if gpus_per_fit > 0 else "cpu")
            if device == "cuda" and gpus_per_fit == 0:
                raise ValueError("--device cuda needs GPUs for the fits: give --gpus-per-fit (e.g. 1 or 0.5)")
            preset_name = args.preset or ("default" if device == "cuda" else "quick")
            config = config_from_arguments(args, preset_name)  # every option checked before any task starts
            print(f"fitting {len(subjects)} subjects on Ray ({gpus:g} GPUs, "
                  f"{ray.cluster_resources().get('CPU', 0):g} CPUs) with preset '{preset_name}' on {device}, "
                  f"{gpus_per_fit:g} GPU and {args.cpus_per_fit:g} CPU a fit -> {args.output}")
            results = run_batch(subjects, args.output, config=config, device=device, preset_name=preset_name,
                                gpus_per_fit=gpus_per_fit, cpus_per_fit=args.cpus_per_fit,
                                max_retries=args.max_retries, evaluate=args.eval, force=args.force,
                                progress=not args.no_progress, test_kill=kill, stop_requested=lambda: bool(stop),
                                kernel_cache=kernel_cache)
    except KeyboardInterrupt as interruption:  # a second signal, or Ctrl-C before the handlers were installed
        return _interrupted(interruption_signal(interruption))
    finally:
        if connected:
            ray.shutdown()
    if stop:
        return _interrupted(stop.signal_number)
    for line in summary_lines(results):
        print(line)
    json_path, csv_path = write_summary(args.output, results)
    print(f"summary: {json_path} and {csv_path}")
    return 1 if any(result["status"] == "failed" for result in results) else 0


def _interrupted(signal_number: int) -> int:
    """Say that the batch was stopped by ``signal_number``; the exit status."""
    print(f"interrupted by {signal.Signals(signal_number).name}: the running fits stopped after their step under "
          "way and wrote their checkpoints; the same command continues the batch", file=sys.stderr)
    return interruption_exit_status(signal_number)


if __name__ == "__main__":
    sys.exit(main())
