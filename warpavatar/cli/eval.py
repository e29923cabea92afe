"""``warpavatar-eval``: measure a fitted avatar on held-out video folders."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from warpavatar.cli.common import avatar_parser, check_output_path, friendly_errors, load_avatar

DESCRIPTION = """Render a fitted avatar with the cameras and poses of a video folder and compare with its frames.

Reports PSNR and SSIM over the full frame (on the folder's background) and inside the ground-truth mask, and
LPIPS when VGG/AlexNet weights are available locally (nothing is downloaded), per frame and as means.
VIDEO_FOLDER may also be a subject folder: then every folder under novel_view/ and novel_pose/ is evaluated.
"""


def build_parser() -> argparse.ArgumentParser:
    parser = avatar_parser("warpavatar-eval", DESCRIPTION, motion=False)
    parser.add_argument("video_folder", type=Path, help="held-out video folder, or a subject folder")
    parser.add_argument("--json", type=Path, default=None, help="write the results (means and per frame) here")
    parser.add_argument("--save-renders", type=Path, default=None,
                        help="write render | ground truth | error images into this folder")
    parser.add_argument("--scale", type=float, default=1.0, help="evaluate at this image scale (default: 1)")
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
    if not args.scale > 0:
        raise ValueError(f"--scale must be positive, got {args.scale}")
    if args.json is not None:
        check_output_path(args.json, "--json", folder=False)
    if args.save_renders is not None:
        check_output_path(args.save_renders, "--save-renders", folder=True)
    from warpavatar import data
    from warpavatar.evaluate import evaluate_avatar, write_json_atomic

    avatar = load_avatar(args)
    folder = args.video_folder
    if (folder / "novel_view").is_dir() or (folder / "novel_pose").is_dir():
        subject = data.load_subject(folder, scale=args.scale)
        videos = ((f"{kind}/{name}", folders[name]) for kind, folders in
                  (("novel_view", subject.novel_view), ("novel_pose", subject.novel_pose)) for name in folders)
    else:
        videos = iter([(folder.name, data.load_video_folder(folder, scale=args.scale))])
    results = {}
    for label, video in videos:
        renders = args.save_renders / label if args.save_renders and len(label.split("/")) > 1 else args.save_renders
        result = evaluate_avatar(avatar, video, save_renders=renders, progress=not args.no_progress,
                                 refine_steps=args.refine_poses)
        results[label] = result
        lpips = f", LPIPS {result['lpips']:.4f}" if result.get("lpips") is not None else ""
        masked = (f"masked PSNR {result['psnr_masked']:.2f} dB, masked SSIM {result['ssim_masked']:.4f}, "
                  if result["psnr_masked"] is not None else "")
        print(f"{label}: {masked}PSNR {result['psnr']:.2f} dB, SSIM {result['ssim']:.4f}{lpips} "
              f"({result['frame_count']} frames, {1000 * result['seconds_per_frame']:.1f} ms/frame)")
        refined = result.get("refined")
        if refined is not None:
            masked = (f"masked PSNR {refined['psnr_masked']:.2f} dB, masked SSIM {refined['ssim_masked']:.4f}, "
                      if refined["psnr_masked"] is not None else "")
            print(f"{label}, poses refined ({refined['steps']} steps a frame): {masked}PSNR {refined['psnr']:.2f} "
                  f"dB, SSIM {refined['ssim']:.4f}")
    if args.json:
        write_json_atomic(args.json, results if len(results) > 1 else next(iter(results.values())))
    return 0


if __name__ == "__main__":
    sys.exit(main())
