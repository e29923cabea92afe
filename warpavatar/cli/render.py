"""``warpavatar-render``: render a fitted avatar driven by a motion to an MP4 or PNG frames."""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

import numpy as np
import torch
import tqdm

from warpavatar.cli.common import avatar_parser, check_output_path, friendly_errors, load_avatar, load_motion_for
from warpavatar.io.output_files import (atomic_path, check_replaceable_folder, disk_full_error, output_lock,
                                        staged_folder)
from warpavatar.model.playback import Player

DESCRIPTION = """Render a fitted avatar animated by a motion, as an MP4 (OpenCV) or a folder of PNG frames.

Cameras: --camera takes a cameras.json (fixed or one per frame); --orbit circles the avatar; by default a
video-folder motion uses its own cameras and other motions an orbit.

Outputs are written under a temporary name beside -o and renamed once complete, so a failure (a full disk
included: one line, exit status 2) leaves nothing half-written. An existing video file is replaced then. An
existing frames folder is replaced only with --overwrite and only if it is an earlier render's (its
.warpavatar-output marker says so) holding nothing else; any other non-empty folder is refused, so no file of
yours is ever deleted. One process at a time writes an output: a second one is refused while the first runs.
"""

FRAMES_KIND = "render-frames"
"""The kind of output a frames folder's marker names."""

VIDEO_SUFFIXES = (".mp4", ".avi", ".mov")
"""Output names that make a video file (the rest are frames folders)."""


def build_parser() -> argparse.ArgumentParser:
    parser = avatar_parser("warpavatar-render", DESCRIPTION, motion=True)
    parser.add_argument("-o", "--output", required=True, type=Path,
                        help="an .mp4 (.avi, .mov) file, or a folder that receives 000000.png, 000001.png, ...")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace the frames folder of an earlier render at -o (a folder warpavatar-render did "
                             "not write is refused even so; a video file is always replaced)")
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
    to_video = args.output.suffix.lower() in VIDEO_SUFFIXES
    check_output_path(args.output, "-o", folder=not to_video)
    if not 1 <= args.size <= 16384:
        raise ValueError(f"--size must be 1 to 16384 pixels, got {args.size}")
    if not all(0.0 <= value <= 1.0 for value in args.background):
        raise ValueError(f"--background must be R G B in 0..1, got {' '.join(map(str, args.background))}")
    with output_lock(args.output, flag="-o"):
        if not to_video:
            check_replaceable_folder(args.output, kind=FRAMES_KIND, overwrite=args.overwrite, name=f"-o {args.output}")
        return render(args, to_video=to_video)


def render(args: argparse.Namespace, *, to_video: bool) -> int:
    """Render the animation of ``main``'s parsed arguments (its output locked and checked); the exit status."""
    from warpavatar.io.animation import motion_time_codes, orbit_cameras, read_cameras_json
    from warpavatar.io.images import write_image

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
    players = {}

    def rendered_frames():
        """The frames in order, as 8-bit RGB images."""
        for t in tqdm.trange(count, disable=args.no_progress, desc="render"):
            bones = torch.as_tensor(motion.bone_transforms[t], dtype=torch.float32, device=device)
            inputs = {name: torch.as_tensor(values[t], device=device) for name, values in part_inputs.items()}
            size = (int(cameras[t].width), int(cameras[t].height))
            if size not in players:  # one player (its buffers, its CUDA graph) per image size
                players[size] = Player(avatar, cameras[t], background=background)
            image, _, _ = players[size].render(bones, camera=cameras[t], inputs=inputs, frame_index=t)
            yield (image.clamp(0, 1).cpu().numpy() * 255).round().astype(np.uint8)

    if to_video:
        written = write_video(output, rendered_frames(), fps=fps)
    else:
        written = 0
        with staged_folder(output, kind=FRAMES_KIND, overwrite=args.overwrite, name=f"-o {output}",
                           overwrite_hint="--overwrite") as folder:
            for t, pixels in enumerate(rendered_frames()):
                write_image(folder / f"{t:06d}.png", pixels, fsync=False)
                written += 1
    print(f"wrote {output} ({written} frames at {fps:g} fps)")
    return 0


def write_video(output: Path, frames, *, fps: float) -> int:
    """Encode ``frames`` (8-bit RGB images of one size) as the MP4 video ``output`` (OpenCV, ``mp4v``), through a
    temporary file that is read back and renamed once complete.

    Returns:
        the number of frames the finished file holds.

    Raises:
        OSError: OpenCV cannot write the file, or the file it finished does not hold every frame (a full disk:
            :class:`~warpavatar.io.output_files.DiskFullError`); nothing is left at ``output`` or beside it.
    """
    import cv2

    from warpavatar.io.images import check_opencv_path  # (OpenCV's log, which reports failed writes, off)

    check_opencv_path(output, "-o")  # OpenCV opens the file itself: a path that is not UTF-8 crashes it
    writer = None
    try:
        with atomic_path(output, suffix=output.suffix) as temporary:
            count = 0
            for pixels in frames:
                if writer is None:
                    writer = cv2.VideoWriter(str(temporary), cv2.VideoWriter_fourcc(*"mp4v"), fps,
                                             (pixels.shape[1], pixels.shape[0]))
                    if not writer.isOpened():
                        raise OSError(f"{output}: OpenCV cannot write this video file")
                writer.write(cv2.cvtColor(pixels, cv2.COLOR_RGB2BGR))
                count += 1
            if writer is not None:
                writer.release()
                writer = None
            written = _video_frame_count(temporary)
            if written != count and _nearly_full(output.parent):
                raise disk_full_error(output)
            if written != count:
                raise OSError(f"{output}: OpenCV finished a video of {written} of its {count} frames; nothing was "
                              "written")
    finally:
        if writer is not None:
            writer.release()
    return written


def _video_frame_count(path: Path) -> int:
    """The frames a video file holds, as OpenCV reads them back (0 for a file it cannot open)."""
    import cv2

    from warpavatar.io.images import native_stderr_silenced

    with native_stderr_silenced():  # FFmpeg may report an unfinished file on the process's stderr itself
        capture = cv2.VideoCapture(str(path))
        try:
            return max(0, int(capture.get(cv2.CAP_PROP_FRAME_COUNT))) if capture.isOpened() else 0
        finally:
            capture.release()


def _nearly_full(folder: Path) -> bool:
    """Whether the file system of ``folder`` has less than 16 MiB free (where a video write stops)."""
    try:
        return shutil.disk_usage(folder).free < 16 * 2**20
    except OSError:
        return False


if __name__ == "__main__":
    sys.exit(main())
