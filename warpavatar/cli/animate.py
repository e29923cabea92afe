"""``warpavatar-animate``: drive a fitted avatar with a motion and write the animation to USD."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import tqdm

from warpavatar.cli.common import default_device, friendly_errors, resolve_device

DESCRIPTION = """Pose a fitted avatar frame by frame with a motion and write the animated Gaussians to USD.

Layouts: 'particlefield' (default) writes one UsdVol.ParticleField3DGaussianSplat prim (the standard schema
for Gaussian splats, read by Omniverse and recent USD tools); 'points' writes a UsdGeom.Points prim with
widths, colours, opacities and primvars for orientations, scales and SH (read by Blender and older tools).
See docs/export.md for every attribute written.
"""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="warpavatar-animate", description=DESCRIPTION,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("avatar", type=Path, help="the fit's output folder (or its avatar.pt)")
    parser.add_argument("--motion", required=True, type=Path,
                        help="motion source: a video folder (its poses.npz), a poses .npz with bone_transforms of "
                             "the same skeleton, or a .bvh file")
    parser.add_argument("-o", "--output", required=True, type=Path, help="the .usdc (or .usd, binary crate) file to write")
    parser.add_argument("--layout", choices=("particlefield", "points"), default="particlefield",
                        help="USD prim layout (default: %(default)s)")
    parser.add_argument("--frames", default=None, metavar="A:B", help="only motion frames A..B-1 (default: all)")
    parser.add_argument("--fps", type=float, default=None, help="time codes per second (default: the motion's)")
    parser.add_argument("--skeleton", action="store_true",
                        help="also write the skeleton and its animation as UsdSkel (Skeleton + SkelAnimation), "
                             "including joints grown by --grow-joints (named grown_<parent>_<k>)")
    parser.add_argument("--name-map", type=Path, default=None,
                        help="BVH only: JSON file mapping avatar joint names to BVH joint names "
                             "(default: same names, case-insensitive); unmapped joints keep their rest pose")
    parser.add_argument("--bvh-scale", type=float, default=None,
                        help="BVH only: metres per BVH unit (default: from the ratio of skeleton heights)")
    parser.add_argument("--bvh-up", choices=("X", "Y", "Z"), default=None, help="BVH only: its up axis (default Y)")
    parser.add_argument("--grown-rotations", type=Path, default=None, metavar="FILE",
                        help="explicit rotations of the joints grown by --grow-joints, one row per motion frame: a .npy "
                             "[T, E, 4] or a .npz with a 'rotations' array, (w, x, y, z) in each grown joint's "
                             "parent rest frame (default: training instants replay their learned rotations, other "
                             "poses keep the grown joints at rest)")
    parser.add_argument("--device", default=default_device(), help="torch device (default: %(default)s)")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    return parser


@friendly_errors
def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    import json

    from warpavatar.animation import parse_frame_range, posed_frames, read_grown_rotations
    from warpavatar.avatar import Avatar
    from warpavatar.io.motion import load_motion
    from warpavatar.io.usd import GaussianUsdWriter

    device = resolve_device(args.device)
    avatar = Avatar.load(args.avatar, device=device)
    name_map = json.loads(args.name_map.read_text()) if args.name_map else None
    motion = load_motion(args.motion, avatar.skeleton, name_map=name_map, frames=parse_frame_range(args.frames),
                         bvh_scale=args.bvh_scale, bvh_up=args.bvh_up)
    fps = args.fps or motion.fps
    grown = None
    if args.grown_rotations is not None:
        grown = read_grown_rotations(args.grown_rotations, frame_count=motion.bone_transforms.shape[0],
                                     joint_count=avatar.grown_joint_count)
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
                              grown_rotations=grown)
        for t, posed in enumerate(tqdm.tqdm(frames, total=frame_count, disable=args.no_progress, desc="animate")):
            writer.write_frame(t, positions=posed["means"].cpu().numpy(), orientations=posed["quats"].cpu().numpy(),
                               scales=posed["scales"].detach().cpu().numpy(),
                               # the skeleton's transforms, then any grown joints' (ToMiE), as posed
                               joint_transforms=posed["bone_transforms"].cpu().numpy() if args.skeleton else None)
    size = args.output.stat().st_size / 2**20
    print(f"wrote {args.output} ({args.layout}, {frame_count} frames at {fps:g} fps, {g.count} Gaussians, "
          f"{size:.1f} MiB) in {time.time() - start:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
