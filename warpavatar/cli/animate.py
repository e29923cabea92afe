"""``warpavatar-animate``: drive a fitted avatar with a motion and write the animation in the format the output's
suffix names (animated USD Gaussians, the rest pose as a 3DGS .ply, or a format another package registers)."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from warpavatar.cli.common import avatar_parser, check_output_path, friendly_errors, load_avatar, load_motion_for
from warpavatar.io import exporters
from warpavatar.io.output_files import output_lock

DESCRIPTION = """Pose a fitted avatar frame by frame with a motion and write the animated Gaussians to USD, or write
its rest pose, in the format the suffix of -o names (the list below).

USD layouts: 'particlefield' (default) writes one UsdVol.ParticleField3DGaussianSplat prim (the standard schema
for Gaussian splats, read by Omniverse and recent USD tools); 'points' writes a UsdGeom.Points prim with
widths, colours, opacities and primvars for orientations, scales and SH (read by Blender and older tools).
Every part of the avatar runs as in a fit (learned secondary dynamics roll the motion out first). A garment
fitted as a sheet (--garment-surface sheet) is also written to USD as an animated mesh, /Avatar/Garment: each
frame, the sheet its Gaussians sit on.
See docs/export.md for every attribute written.

The file is written under a temporary name of its own beside -o and renamed once complete: an existing file at
-o is replaced only then, and a failure (a full disk included: one line, exit status 2) leaves it as it was. One
process at a time writes an output: a second one is refused while the first runs.
"""

MOTION_OPTIONS = {"motion": "--motion", "frames": "--frames", "fps": "--fps", "name_map": "--name-map",
                  "bvh_scale": "--bvh-scale", "bvh_up": "--bvh-up", "grown_rotations": "--grown-rotations"}
"""The options that only a format which takes a motion uses (parsed name -> flag)."""


def _formats_text() -> str:
    """The registered formats, for the description."""
    return ("Formats, chosen by the suffix of -o (and by --layout where a suffix has several):\n"
            + "\n".join(exporters.describe_exporters()) + "\n")


def build_parser() -> argparse.ArgumentParser:
    exporters.load_entry_points()  # formats other packages declare, so that --help lists them too
    parser = avatar_parser("warpavatar-animate", DESCRIPTION + "\n" + _formats_text(), motion=True)
    parser.add_argument("-o", "--output", required=True, type=Path,
                        help="the file to write; its suffix chooses the format: .usdc (or .usd, binary crate; .usda, "
                             "text) for USD, .ply for the rest pose (an existing file is replaced once the new one "
                             "is complete)")
    parser.add_argument("--layout", choices=exporters.exporter_layouts(), default=None,
                        help="the layout, for a suffix with several: USD's prim layout (default: particlefield)")
    parser.add_argument("--skeleton", action="store_true",
                        help="also write the skeleton and its animation as UsdSkel (Skeleton + SkelAnimation), "
                             "including joints grown by --grow-joints (named grown_<parent>_<k>)")
    parser.add_argument("--keep-floaters", action="store_true",
                        help="for .ply: keep every Gaussian (by default those whose centre lies more than 25%% of the "
                             "skeleton's height from every bone, or with opacity below 1/255, are left out, as in "
                             "the fit's canonical.ply; docs/export.md)")
    return parser


@friendly_errors
def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    check_output_path(args.output, "-o", folder=False)
    exporter = exporters.exporter_for(args.output, layout=args.layout, flag="-o")
    check_options(args, exporter)
    with output_lock(args.output, flag="-o"):
        return animate(args, exporter=exporter)


def check_options(args: argparse.Namespace, exporter: exporters.Exporter) -> None:
    """Refuse options the chosen format does not use: a motion's for a rest-pose format, ``--skeleton`` for one
    that cannot hold it.

    Raises:
        ValueError: naming ``-o``, its format and the options given.
    """
    unused = [] if exporter.animated else [flag for name, flag in MOTION_OPTIONS.items()
                                           if getattr(args, name) is not None]
    if args.skeleton and not exporter.writes_skeleton:
        unused.append("--skeleton")
    if args.keep_floaters and not exporter.drops_floaters:
        raise ValueError(f"-o {args.output}: the {exporter.name} format writes every Gaussian, so --keep-floaters "
                         "would not be used; leave it out")
    if unused:
        what = "holds no skeleton" if exporter.animated else "writes the rest pose only"
        raise ValueError(f"-o {args.output}: the {exporter.name} format {what}, so {', '.join(unused)} would not be "
                         f"used; leave {'it' if len(unused) == 1 else 'them'} out, or give -o the suffix of another "
                         "format (--help lists them)")


def animate(args: argparse.Namespace, *, exporter: exporters.Exporter) -> int:
    """Write the output of ``main``'s parsed arguments in ``exporter``'s format (its output locked); the exit
    status."""
    avatar = load_avatar(args)
    motion = None
    if exporter.animated:
        loaded, _, part_inputs = load_motion_for(avatar, args)
        motion = exporters.ExportMotion.from_motion(loaded, fps=args.fps, part_inputs=part_inputs)
    start = time.time()
    args.output.parent.mkdir(parents=True, exist_ok=True)
    summary = exporter.export(avatar, args.output, motion=motion,
                              options=exporters.ExportOptions(skeleton=args.skeleton, progress=not args.no_progress,
                                                              keep_floaters=args.keep_floaters))
    size = args.output.stat().st_size / 2**20
    print(f"wrote {args.output} ({summary}, {size:.1f} MiB) in {time.time() - start:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
