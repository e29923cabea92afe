"""``warpavatar-render``: render a fitted avatar driven by a motion to an MP4 or PNG frames."""

from __future__ import annotations

import argparse
import os
import shutil
import sys
from pathlib import Path

import numpy as np
import torch
import tqdm

from warpavatar.cli.common import avatar_parser, check_output_path, friendly_errors, load_avatar, load_motion_for
from warpavatar.model.playback import Player

DESCRIPTION = """Render a fitted avatar animated by a motion, as an MP4 (OpenCV) or a folder of PNG frames.

Cameras: --camera takes a cameras.json (fixed or one per frame); --orbit circles the avatar; by default a
video-folder motion uses its own cameras and other motions an orbit.
"""


def build_parser() -> argparse.ArgumentParser:
    parser = avatar_parser("warpavatar-render", DESCRIPTION, motion=True)
    parser.add_argument("-o", "--output", required=True, type=Path,
                        help="an .mp4 file, or a folder that receives 000000.png, 000001.png, ...")
    camera = parser.add_mutually_exclusive_group()
    camera.add_argument("--camera", type=Path, default=None, help="cameras.json to render through")
    camera.add_argument("--orbit", action="store_true", help="circle the avatar once over the animation")
    parser.add_argument("--size", type=int, default=512, help="orbit image width and height in pixels (default 512)")
    parser.add_argument("--background", type=float, nargs=3, default=(0.0, 0.0, 0.0), metavar=("R", "G", "B"),
                        help="background colour in 0..1 (default black)")
    return parser


@friendly_errors
@torch.no_grad()
def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    to_video = args.output.suffix.lower() in (".mp4", ".avi", ".mov")
    check_output_path(args.output, "-o", folder=not to_video)
    if not 1 <= args.size <= 16384:
        raise ValueError(f"--size must be 1 to 16384 pixels, got {args.size}")
    if not all(0.0 <= value <= 1.0 for value in args.background):
        raise ValueError(f"--background must be R G B in 0..1, got {' '.join(map(str, args.background))}")
    import cv2

    from warpavatar.io.animation import motion_time_codes, orbit_cameras, read_cameras_json

    avatar = load_avatar(args)
    device = avatar.gaussians.means.device
    motion, frames, part_inputs = load_motion_for(avatar, args)
    count = motion.bone_transforms.shape[0]
    if args.camera:
        cameras = read_cameras_json(args.camera, count)
    elif not args.orbit and args.motion.is_dir():
        from warpavatar.data import load_video_folder

        cameras = load_video_folder(args.motion).cameras
        cameras = cameras[frames] if frames is not None else cameras
    else:
        cameras = orbit_cameras(avatar.skeleton, count, width=args.size, height=args.size)
    # rows of a motion that keeps every k-th frame of its clock lie k frames apart: the video plays them at
    # fps / k, so the motion keeps its captured speed (as the USD export's time codes do)
    codes = motion_time_codes(motion.frame_ids[:count])
    row_step = float(codes[-1] - codes[0]) / (count - 1) if count > 1 else 1.0
    fps = args.fps or motion.fps / max(row_step, 1.0)
    background = torch.tensor(args.background, dtype=torch.float32, device=device)
    avatar.prepare_sequence(motion.bone_transforms, frame_ids=motion.frame_ids, fps=motion.fps,
                            progress=not args.no_progress)

    output = args.output
    output.parent.mkdir(parents=True, exist_ok=True)
    tmp = output.with_name(output.stem + ".tmp" + output.suffix) if to_video else output.with_name(output.name + ".tmp")
    writer = None
    if not to_video:
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir(parents=True)
    players = {}
    try:
        for t in tqdm.trange(count, disable=args.no_progress, desc="render"):
            bones = torch.as_tensor(motion.bone_transforms[t], dtype=torch.float32, device=device)
            inputs = {name: torch.as_tensor(values[t], device=device) for name, values in part_inputs.items()}
            size = (int(cameras[t].width), int(cameras[t].height))
            if size not in players:  # one player (its buffers, its CUDA graph) per image size
                players[size] = Player(avatar, cameras[t], background=background)
            image, _, _ = players[size].render(bones, camera=cameras[t], inputs=inputs, frame_index=t)
            pixels = cv2.cvtColor((image.clamp(0, 1).cpu().numpy() * 255).round().astype(np.uint8), cv2.COLOR_RGB2BGR)
            if to_video:
                if writer is None:
                    writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), fps,
                                             (pixels.shape[1], pixels.shape[0]))
                    if not writer.isOpened():
                        raise ValueError(f"{output}: OpenCV cannot write this video file")
                writer.write(pixels)
            else:
                cv2.imwrite(str(tmp / f"{t:06d}.png"), pixels)
        if writer is not None:
            writer.release()
            writer = None
        if not to_video and output.exists():
            shutil.rmtree(output)
        os.replace(tmp, output)
    finally:
        if writer is not None:
            writer.release()
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True) if tmp.is_dir() else tmp.unlink()
    print(f"wrote {output} ({count} frames at {fps:g} fps)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
