"""``warpavatar-animate``: drive a fitted avatar with a motion and write the animation to USD."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import tqdm

from warpavatar.cli.common import avatar_parser, check_output_path, friendly_errors, load_avatar, load_motion_for
from warpavatar.io.output_files import output_lock

DESCRIPTION = """Pose a fitted avatar frame by frame with a motion and write the animated Gaussians to USD.

Layouts: 'particlefield' (default) writes one UsdVol.ParticleField3DGaussianSplat prim (the standard schema
for Gaussian splats, read by Omniverse and recent USD tools); 'points' writes a UsdGeom.Points prim with
widths, colours, opacities and primvars for orientations, scales and SH (read by Blender and older tools).
Every part of the avatar runs as in a fit (learned secondary dynamics roll the motion out first).
See docs/export.md for every attribute written.

The file is written under a temporary name of its own beside -o and renamed once complete: an existing file at
-o is replaced only then, and a failure (a full disk included: one line, exit status 2) leaves it as it was. One
process at a time writes an output: a second one is refused while the first runs.
"""


def build_parser() -> argparse.ArgumentParser:
    parser = avatar_parser("warpavatar-animate", DESCRIPTION, motion=True)
    parser.add_argument("-o", "--output", required=True, type=Path,
                        help="the .usdc (or .usd, binary crate) file to write (an existing file is replaced once the "
                             "new one is complete)")
    parser.add_argument("--layout", choices=("particlefield", "points"), default="particlefield",
                        help="USD prim layout (default: %(default)s)")
    parser.add_argument("--skeleton", action="store_true",
                        help="also write the skeleton and its animation as UsdSkel (Skeleton + SkelAnimation), "
                             "including joints grown by --grow-joints (named grown_<parent>_<k>)")
    return parser


@friendly_errors
def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    check_output_path(args.output, "-o", folder=False)
    with output_lock(args.output, flag="-o"):
        return animate(args)


def animate(args: argparse.Namespace) -> int:
    """Write the animation of ``main``'s parsed arguments (its output locked); the exit status."""
    from warpavatar.io.animation import motion_time_codes, posed_frames
    from warpavatar.io.usd import GaussianUsdWriter

    avatar = load_avatar(args)
    motion, _, part_inputs = load_motion_for(avatar, args)
    fps = args.fps or motion.fps
    skeleton = avatar.skeleton
    up_axis = "XYZ"[int(abs(skeleton.up).argmax())]
    g = avatar.gaussians
    start = time.time()
    frame_count = motion.bone_transforms.shape[0]
    with GaussianUsdWriter(args.output, layout=args.layout, gaussian_count=g.count, sh_degree=g.sh_degree,
                           opacities=g.opacities.detach().cpu().numpy(),
                           sh_coeffs=g.sh_coefficients().detach().cpu().numpy(), fps=fps, up_axis=up_axis,
                           meters_per_unit=1.0, skeleton=avatar.rig() if args.skeleton else None) as writer:
        frames = posed_frames(avatar, motion.bone_transforms, frame_ids=motion.frame_ids, fps=motion.fps,
                              part_inputs=part_inputs)
        time_codes = motion_time_codes(motion.frame_ids)  # frames of the motion's clock, played at fps
        for t, posed in enumerate(tqdm.tqdm(frames, total=frame_count, disable=args.no_progress, desc="animate")):
            writer.write_frame(int(time_codes[t]), positions=posed["means"].cpu().numpy(),
                               orientations=posed["quats"].cpu().numpy(), scales=posed["scales"].detach().cpu().numpy(),
                               # the skeleton's transforms, then any grown joints' (ToMiE), as posed
                               joint_transforms=posed["bone_transforms"].cpu().numpy() if args.skeleton else None)
    size = args.output.stat().st_size / 2**20
    print(f"wrote {args.output} ({args.layout}, {frame_count} frames at {fps:g} fps, {g.count} Gaussians, "
          f"{size:.1f} MiB) in {time.time() - start:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
