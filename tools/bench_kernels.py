"""Kernel micro-benchmarks of warpavatar: ``python tools/bench_kernels.py MODE [options]``.

Modes: ``splat`` (rasterizer, against gsplat when importable), ``knn``, ``springs``, ``skinning``
(sample_grid and lbs), ``shading`` (view-dependent SH colour, fused kernel against op-by-op torch), ``usd`` (USD animation writing, CPU), ``dynamics`` (SMAD's learned dynamics: rollout
and training window), ``cloth`` (one frame of the simulated garment, substeps included, and the capsule
collision), ``sheet_cloth`` (a rollout frame and a training window of the triangle-mesh cloth, a 2k-vertex skirt), ``avatar`` (a fitted avatar: rasterizer against gsplat on its posed Gaussians at the training size and
1080p, the training step eager and captured with its launches and host reads, playback FPS; ``--avatar``,
``--video``, ``--garment``: a garment forced on the fresh avatar, so the step includes the cloth's window),
``all``. Each mode lives in ``tools/bench_<mode>.py`` and returns table rows; this script prints them as a
markdown table with the device and date, and appends them to ``--record`` (default ``BENCHMARKS.md``) when
asked, so runs can be compared over time.
"""

from __future__ import annotations

import argparse
import datetime
import importlib
import platform
import sys

import torch

from bench_common import markdown_table

MODES = ("splat", "knn", "springs", "skinning", "shading", "usd", "dynamics", "cloth", "sheet_cloth", "avatar")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("mode", choices=MODES + ("all",), help="which kernel family to benchmark")
    parser.add_argument("--device", default="cuda:0" if torch.cuda.is_available() else "cpu",
                        help="torch device to run on (default: cuda:0 when available, else cpu)")
    parser.add_argument("--quick", action="store_true",
                        help="small sizes and few repetitions: checks that the benchmark runs, numbers mean little")
    parser.add_argument("--record", metavar="FILE", default=None,
                        help="append the tables, with device, date and command, to this markdown file")
    parser.add_argument("--avatar", metavar="AVATAR_PT", default=None,
                        help="avatar mode: a fitted avatar.pt (default: the avatar a fresh fit of --video starts from)")
    parser.add_argument("--video", metavar="FOLDER", default=None,
                        help="avatar mode: the avatar's training video folder (default: the built-in demo subject)")
    parser.add_argument("--garment", action="store_true",
                        help="avatar mode: force a simulated garment on the fresh avatar (hung from the root joint), "
                             "so that the training step includes the cloth's window (default: off)")
    parser.add_argument("--matmul-precision", choices=("tf32", "fp32"), default=None,
                        help="avatar mode: precision of the MLPs' float32 GEMMs in the training step and in playback "
                             "(warpavatar-fit --matmul-precision; default: the fitted avatar's config, else tf32)")
    parser.add_argument("--rounds", type=int, default=2,
                        help="splat and avatar modes: time the rasterizer (ours and gsplat) in this many interleaved "
                             "rounds, the order reversed every other round, and print each time and ratio as one "
                             "value or its range over the rounds (default: 2)")
    parser.add_argument("--replay", choices=("address", "owned", "off"), default="address",
                        help="splat and avatar modes: how repeated rasterizer passes skip their host work "
                             "(warpavatar.ops.rasterizer_replays): address (default, as warpavatar runs) replays a "
                             "pass whose buffers' addresses repeat from a CUDA graph; owned replays a repeated shape "
                             "from a graph holding its own buffers; off launches every kernel from Python")
    args = parser.parse_args(argv)
    if args.rounds < 1:
        parser.error(f"--rounds must be >= 1, got {args.rounds}")
    from warpavatar._src.splat import rasterizer_replays  # noqa: PLC0415

    rasterizer_replays(mode=args.replay)

    modes = MODES if args.mode == "all" else (args.mode,)
    if args.device.startswith("cuda"):
        device_name = torch.cuda.get_device_name(torch.device(args.device))
    else:
        device_name = platform.processor() or platform.machine()
    header = (f"## {', '.join(modes)} on {device_name} ({args.device}), "
              f"{datetime.datetime.now(datetime.timezone.utc).strftime('%Y-%m-%d %H:%M UTC')}\n\n"
              f"Command: `python tools/bench_kernels.py {' '.join(argv if argv is not None else sys.argv[1:])}`; "
              f"torch {torch.__version__}\n")
    out = [header]
    for mode in modes:
        module = importlib.import_module(f"bench_{mode}")
        extra = ({"avatar": args.avatar, "video": args.video, "garment": args.garment,
                  "matmul_precision": args.matmul_precision} if mode == "avatar" else {})
        if mode in ("splat", "avatar"):
            extra["rounds"] = args.rounds
        rows = module.run(device=args.device, quick=args.quick, **extra)
        out.append(f"### {mode}\n\n{markdown_table(rows)}\n")
        print(out[-1], flush=True)
    text = "\n".join(out)
    if args.record:
        with open(args.record, "a", encoding="utf-8") as f:
            f.write(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
