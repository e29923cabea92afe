"""``warpavatar-fit``: fit an animatable Gaussian avatar to a video folder."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from warpavatar.cli.common import default_device, friendly_errors, resolve_device
from warpavatar.fit.arguments import add_config_arguments, config_from_arguments
from warpavatar.fit.presets import preset_names

DESCRIPTION = """Fit an animatable 3D Gaussian avatar to a video folder (see docs/data.md for the format).

Outputs in the output folder: avatar.pt (the avatar: Gaussians, skinning field, skeleton, its optional parts,
config; loads back with warpavatar.model.Avatar.load), canonical.ply (the canonical Gaussians with the 3DGS
attribute names), config.json, train_log.jsonl (one JSON line per logged step: every loss term by name),
training_poses.npz (the poses fitted on, as a poses.npz: warpavatar-view plays it), checkpoint.pt (to resume)
and previews/ (render | ground truth for a few training frames).

Options: the main ones first, then the core's groups, then one group per optional part (extension) with its
research knobs. Each overrides the preset's value; --help shows the default and where a preset differs.
"""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="warpavatar-fit", description=DESCRIPTION,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("video_folder", nargs="?", type=Path,
                        help="the video folder to fit (or a subject folder holding train/); omit with --demo")
    parser.add_argument("-o", "--output", type=Path, default=None,
                        help="output folder (default: ./warpavatar-out/<folder name>)")
    parser.add_argument("--preset", choices=preset_names(), default=None,
                        help="named configuration: 'default' (quality, GPU) or 'quick' (small, CPU, minutes); "
                             "default: 'default' on CUDA, 'quick' on CPU and with --demo")
    parser.add_argument("--device", default=default_device(), help="torch device: cpu or cuda (default: %(default)s)")
    parser.add_argument("--resume", action="store_true",
                        help="continue from checkpoint.pt in the output folder (same options required)")
    parser.add_argument("--demo", action="store_true",
                        help="fit the small built-in demo subject (a reduced robot) and evaluate it on its held-out "
                             "view and pose")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    add_config_arguments(parser)
    return parser


@friendly_errors
def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    from warpavatar import data
    from warpavatar.evaluate import evaluate_avatar, write_json_atomic
    from warpavatar.fit import Trainer

    device = resolve_device(args.device)
    preset_name = args.preset or ("default" if device.type == "cuda" and not args.demo else "quick")
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
    video = data.load_video_folder(folder, scale=config.image_scale)
    print(f"fitting {folder} ({video.frame_count} frames, {video.width}x{video.height}, "
          f"{video.skeleton.joint_count} joints) on {device} with preset '{preset_name}' -> {output}")
    start = time.time()
    trainer = Trainer(video, config, output, device=device)
    trainer.fit(resume=args.resume, progress=not args.no_progress)
    minutes = (time.time() - start) / 60
    print(f"done in {minutes:.1f} min: {trainer.gaussians.count} Gaussians; avatar at {output / 'avatar.pt'}")
    for line in trainer.summary_lines():
        print(line)
    if args.demo:
        subject = data.load_subject(subject_root)
        results = {}
        for kind, folders in (("novel_view", subject.novel_view), ("novel_pose", subject.novel_pose)):
            for name in folders:
                held_out = folders[name]
                result = evaluate_avatar(trainer.avatar, held_out, progress=False)
                results[f"{kind}/{name}"] = {k: v for k, v in result.items() if k != "frames"}
                print(f"  {kind}/{name}: masked PSNR {result['psnr_masked']:.2f} dB, "
                      f"full-frame PSNR {result['psnr']:.2f} dB, SSIM {result['ssim']:.4f}")
        write_json_atomic(output / "demo_eval.json", results)
        print(f"demo result in {output.resolve()} (avatar.pt, canonical.ply, previews/, demo_eval.json)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
