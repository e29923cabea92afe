"""``warpavatar-prepare``: turn a phone video (or several calibrated videos) into a video folder, offline.

Monocular: ``warpavatar-prepare clip.mp4 -o subject/`` writes ``subject/train/``. Multi-view:
``warpavatar-prepare cam01.mp4 cam02.mp4 ... --calibration Calib.qca.txt -o subject/`` writes the first video to
``subject/train/`` and every other one to ``subject/novel_view/<video name>/``, all sharing one skeleton and one
pose sequence in the calibration's world frame. The work is :func:`warpavatar.prepare.pipeline.prepare_subject`'s;
docs/prepare.md describes every step and its conventions. ``python -m warpavatar.prepare`` runs the same command.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from warpavatar.prepare.pipeline import prepare_subject
from warpavatar.prepare.skeleton_fit import PoseSmoothing

__all__ = ["main"]


def _build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="warpavatar-prepare",
        description="Turn a video of a person (or several calibrated, synchronized videos) into a warpavatar "
                    "video folder: frames, person masks, cameras, a fitted skeleton and its per-frame bone "
                    "transforms. Runs offline; needs the 'prepare' extra (MediaPipe 0.10.21).",
    )
    parser.add_argument("videos", nargs="+", type=Path, metavar="VIDEO",
                        help="video file(s); the first is the training view, others become novel views")
    parser.add_argument("-o", "--output", type=Path, required=True, metavar="FOLDER", help="subject folder to write")
    parser.add_argument("--calibration", type=Path, metavar="FILE",
                        help="camera calibration: OpenCV-style .toml or Qualisys .qca.txt (needed for several videos)")
    parser.add_argument("--focal-px", type=float, metavar="F",
                        help="focal length in pixels of the original video (monocular; default 26/36 of the long side)")
    parser.add_argument("--max-size", type=int, default=1024, metavar="PX",
                        help="resize frames so the long side is at most PX pixels (default 1024)")
    parser.add_argument("--start", type=int, default=0, metavar="S", help="first frame to use (default 0)")
    parser.add_argument("--frames", type=int, metavar="N", help="number of frames to use (default: all)")
    parser.add_argument("--stride", type=int, default=1, metavar="K", help="use every K-th frame (default 1)")
    parser.add_argument("--novel-view-stride", type=int, default=1, metavar="K",
                        help="write every K-th frame into the novel_view folders (default 1)")
    parser.add_argument("--no-smoothing", action="store_true", help="keep the raw per-frame fit")
    parser.add_argument("--license", type=Path, metavar="FILE", help="copied to FOLDER/LICENSE.txt")
    parser.add_argument("--overwrite", action="store_true", help="replace a non-empty output folder")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    return parser


def main(argv: list[str] | None = None) -> int:
    """Console entry point of ``warpavatar-prepare``; returns the exit status."""
    arguments = _build_parser().parse_args(argv)
    from warpavatar.prepare.landmarks import MediaPipeUnavailableError

    try:
        report = prepare_subject(
            arguments.videos, arguments.output, calibration=arguments.calibration, focal_px=arguments.focal_px,
            max_size=arguments.max_size, start=arguments.start, frame_count=arguments.frames,
            stride=arguments.stride, novel_view_stride=arguments.novel_view_stride,
            smoothing=None if arguments.no_smoothing else PoseSmoothing(), license_file=arguments.license,
            overwrite=arguments.overwrite, progress=not arguments.quiet,
        )
    except MediaPipeUnavailableError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    except (ValueError, FileNotFoundError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 1
    print(f"wrote {arguments.output} ({report['mode']}, {report['frames']} frames, {report['timings']['total_s']} s)")
    for folder, meta in report["folders"].items():
        error = meta["reprojection_error_px"]
        print(f"  {folder}: reprojection error median {error['median']} px, p90 {error['p90']} px")
    jitter = report["jitter"]
    print(f"  jitter (median {jitter['unit']}): {jitter['smoothed']['median']} smoothed, "
          f"{jitter['raw_fit']['median']} raw")
    return 0


if __name__ == "__main__":
    sys.exit(main())
