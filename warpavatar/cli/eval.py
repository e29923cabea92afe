"""``warpavatar-eval``: measure a fitted avatar on held-out video folders."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from warpavatar.cli.common import (avatar_parser, check_output_path, cpu_torch_settings, friendly_errors, load_avatar,
                                   resolve_device)
from warpavatar.io.output_files import output_lock, staged_folder

DESCRIPTION = """Render a fitted avatar with the cameras and poses of a video folder and compare with its frames.

Reports PSNR and SSIM over the full frame (on the folder's background) and inside the ground-truth mask, the
floater share (the share of the rendered opacity outside the mask dilated by 3 pixels: floaters, or a blur that
hides a misplaced figure), and LPIPS when VGG/AlexNet weights are available locally (nothing is downloaded),
per frame and as means.
VIDEO_FOLDER may also be a subject folder: then every folder under novel_view/ and novel_pose/ is evaluated.
Scores are computed at the fit's training resolution (its image_scale, as warpavatar-fit --demo and
warpavatar-fit-many --eval compute theirs) unless --scale says otherwise, and each line names the resolution.
Each line also gives the time per frame of the render and of the metrics apart.
"""

RENDERS_KIND = "eval-renders"
"""The kind of output the marker of a --save-renders folder names."""


def build_parser() -> argparse.ArgumentParser:
    parser = avatar_parser("warpavatar-eval", DESCRIPTION, motion=False)
    parser.add_argument("video_folder", type=Path, help="held-out video folder, or a subject folder")
    parser.add_argument("--json", type=Path, default=None, help="write the results (means and per frame) here")
    parser.add_argument("--save-renders", type=Path, default=None,
                        help="write render | ground truth | error images into this folder, a new one (assembled under "
                             "a temporary name and renamed once complete)")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace the --save-renders folder of an earlier evaluation (a folder warpavatar-eval did "
                             "not write is refused even so)")
    parser.add_argument("--scale", type=float, default=None,
                        help="evaluate at this image scale (default: the fit's image_scale, read from config.json "
                             "beside the avatar, so the scores are at the training resolution; 1 without one)")
    parser.add_argument("--refine-poses", type=int, default=0, metavar="STEPS",
                        help="also optimize each frame's pose against its ground truth for STEPS Adam steps with the "
                             "avatar frozen (test-time refinement, for estimated poses), and report the metrics "
                             "with and without it; the saved renders are then the refined ones (default: 0, off)")
    return parser


@friendly_errors
def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if args.refine_poses < 0:
        raise ValueError(f"--refine-poses takes a number of steps >= 0, got {args.refine_poses}")
    if args.scale is not None and not args.scale > 0:
        raise ValueError(f"--scale must be positive, got {args.scale}")
    if args.json is not None:
        check_output_path(args.json, "--json", folder=False)
    if args.save_renders is None:
        return evaluate_folders(args, renders=None)
    check_output_path(args.save_renders, "--save-renders", folder=True)
    with output_lock(args.save_renders, flag="--save-renders"), staged_folder(
            args.save_renders, kind=RENDERS_KIND, overwrite=args.overwrite, name=f"--save-renders {args.save_renders}",
            overwrite_hint="--overwrite") as renders:
        return evaluate_folders(args, renders=renders)


def evaluate_folders(args: argparse.Namespace, *, renders: Path | None) -> int:
    """Evaluate as ``main``'s parsed arguments say, saving the renders under ``renders`` (the staged
    ``--save-renders`` folder) unless it is None; the exit status."""
    from warpavatar.evaluate import write_json_atomic

    with cpu_torch_settings(resolve_device(args.device)):  # one torch thread on the CPU, as a fit
        results = _evaluate_and_print(args, renders=renders)
    if args.json:
        write_json_atomic(args.json, results if len(results) > 1 else next(iter(results.values())))
    return 0


def _evaluate_and_print(args: argparse.Namespace, *, renders: Path | None) -> dict[str, dict]:
    """Evaluate every folder ``args`` names, printing one line of scores (and one of timings) per folder."""
    from warpavatar import data
    from warpavatar.evaluate import evaluate_avatar, score_line

    avatar = load_avatar(args)
    scale = args.scale if args.scale is not None else fit_image_scale(args.avatar)
    folder = args.video_folder
    if (folder / "novel_view").is_dir() or (folder / "novel_pose").is_dir():
        subject = data.load_subject(folder, scale=scale)
        videos = ((f"{kind}/{name}", folders[name]) for kind, folders in
                  (("novel_view", subject.novel_view), ("novel_pose", subject.novel_pose)) for name in folders)
    else:
        videos = iter([(folder.name, data.load_video_folder(folder, scale=scale))])
    results = {}
    for label, video in videos:
        folder_renders = renders / label if renders and len(label.split("/")) > 1 else renders
        result = evaluate_avatar(avatar, video, save_renders=folder_renders, progress=not args.no_progress,
                                 refine_steps=args.refine_poses)
        if not results and result.get("lpips_unavailable"):
            print(f"LPIPS not computed: {result['lpips_unavailable']}")
        results[label] = result
        print(score_line(label, result))
        refined = result.get("refined")
        if refined is not None:
            print(score_line(f"{label}, poses refined ({refined['steps']} steps a frame)",
                             {**refined, "resolution": result["resolution"]}))
        print(f"  {timing_line(result)}")
    return results


def timing_line(result: dict) -> str:
    """The time per frame of an evaluation, render and metrics apart: ``"12 frames; per frame: render 341 ms,
    metrics 52 ms"`` (and the test-time refinement when it ran)."""
    parts = [f"render {1000 * result['render_seconds_per_frame']:.0f} ms",
             f"metrics {1000 * result['metric_seconds_per_frame']:.0f} ms"]
    if "refine_seconds_per_frame" in result:
        parts.append(f"pose refinement {1000 * result['refine_seconds_per_frame']:.0f} ms")
    return f"{result['frame_count']} frames; per frame: {', '.join(parts)}"


def fit_image_scale(avatar_path: Path) -> float:
    """The ``image_scale`` the avatar was fitted at, from the fit's ``config.json`` beside ``avatar_path`` (its
    output folder or avatar file); 1 when there is none (an avatar file on its own).

    Raises:
        ValueError: a config.json that cannot be read or holds no valid image_scale (the message names it).
    """
    folder = avatar_path if avatar_path.is_dir() else avatar_path.parent
    path = folder / "config.json"
    if not path.is_file():
        return 1.0
    try:
        scale = json.loads(path.read_text(encoding="utf-8")).get("image_scale", 1.0)
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, AttributeError) as error:
        raise ValueError(f"{path}: cannot be read as the fit's config ({error}); give --scale") from None
    if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not scale > 0:
        raise ValueError(f"{path}: image_scale must be a positive number, got {scale!r}; give --scale")
    return float(scale)


if __name__ == "__main__":
    sys.exit(main())
