"""Fit a benchmark subject on its train/ folder and evaluate every held-out folder: the avatar-quality table.

    python tools/fit_benchmark.py SUBJECT -o OUT [--preset default|quick] [--device cuda] [--eval-refine-poses STEPS]
        [fit flags...]

SUBJECT holds train/, novel_view/* and novel_pose/* (docs/FORMAT.md). Any other flag is passed to warpavatar-fit's
configuration (e.g. --iterations 8000 --sh-degree 1). Prints one markdown row per held-out folder (masked and
full-frame PSNR/SSIM, fit time, Gaussian count, render time; with ``--eval-refine-poses`` also the masked PSNR and
SSIM after test-time pose refinement, as ``warpavatar-eval --refine-poses`` reports them) and writes
OUT/benchmark.json.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

from warpavatar import data
from warpavatar.evaluate import evaluate_avatar, write_json_atomic
from warpavatar.fit import Trainer, load_training_video
from warpavatar.fit.arguments import add_config_arguments, config_from_arguments


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("subject", type=Path, help="subject folder with train/, novel_view/, novel_pose/")
    parser.add_argument("-o", "--output", type=Path, required=True, help="output folder of the fit")
    parser.add_argument("--preset", default="default", help="fit preset (default: %(default)s)")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu", help="torch device")
    parser.add_argument("--label", default=None, help="name of this run in the table (default: subject name)")
    parser.add_argument("--eval-refine-poses", type=int, default=0, metavar="STEPS",
                        help="also report every held-out folder after test-time pose refinement: STEPS Adam steps "
                             "a frame with the avatar frozen, the protocol of the PeopleSnapshot papers for "
                             "estimated poses (default: %(default)s, off)")
    add_config_arguments(parser)
    args = parser.parse_args(argv)
    if args.eval_refine_poses < 0:
        parser.error(f"--eval-refine-poses must be >= 0, got {args.eval_refine_poses}")
    config = config_from_arguments(args, args.preset)
    label = args.label or args.subject.name

    video = load_training_video(args.subject / "train", config)
    start = time.time()
    trainer = Trainer(video, config, args.output, device=args.device)
    trainer.fit(progress=False)
    if args.device.startswith("cuda"):
        torch.cuda.synchronize()
    fit_minutes = (time.time() - start) / 60
    full_scale = data.load_subject(args.subject)
    rows = []
    held_out = [("train", "", full_scale.train)]  # the fit itself, for comparison with the held-out folders
    for kind, folders in (("novel_view", full_scale.novel_view), ("novel_pose", full_scale.novel_pose)):
        held_out += [(kind, name, folders[name]) for name in folders]
    for kind, name, folder in held_out:
        steps = args.eval_refine_poses if kind != "train" else 0
        result = evaluate_avatar(trainer.avatar, folder, progress=False, refine_steps=steps)
        row = {"run": label, "folder": f"{kind}/{name}".rstrip("/"), "psnr_masked": result["psnr_masked"],
               "psnr": result["psnr"], "ssim_masked": result["ssim_masked"], "ssim": result["ssim"],
               "fit_min": fit_minutes, "gaussians": trainer.gaussians.count,
               "render_ms": 1000 * result["render_seconds_per_frame"]}
        if args.eval_refine_poses:  # the fit's own frames are not refined again: "-"
            refined = result.get("refined", {})
            row.update(refined_psnr_masked=refined.get("psnr_masked", "-"),
                       refined_ssim_masked=refined.get("ssim_masked", "-"))
        rows.append(row)
    write_json_atomic(args.output / "benchmark.json", {"config": config.to_dict(), "device": args.device,
                                                       "rows": rows})
    for row in rows:
        print("| " + " | ".join(f"{v:.3f}" if isinstance(v, float) else str(v) for v in row.values()) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
