"""``warpavatar-render``: render a fitted avatar driven by a motion to an MP4 or PNG frames."""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
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

DESCRIPTION = """Render a fitted avatar animated by a motion, as an H.264 video (.mp4, .mov, .avi) or a folder of
PNG frames.

Cameras: --camera takes a cameras.json (fixed or one per frame); --orbit circles the avatar once, starting at
the training camera so the first frame shows what that camera filmed (with --pose, a turntable of one still pose);
by default a video-folder motion uses its own cameras and other motions an orbit.

Videos are H.264 (yuv420p, an odd side padded by one pixel; .mp4 and .mov with their index first), written by
the ffmpeg that the imageio-ffmpeg package ships: they play in browsers, chat clients and READMEs.

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

VIDEO_CRF = 18
"""libx264's constant rate factor for videos (0 lossless .. 51 worst; 18 looks lossless to most viewers)."""


def build_parser() -> argparse.ArgumentParser:
    parser = avatar_parser("warpavatar-render", DESCRIPTION, motion=True)
    parser.add_argument("-o", "--output", required=True, type=Path,
                        help="an .mp4 (.avi, .mov) file, or a folder that receives 000000.png, 000001.png, ...")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace the frames folder of an earlier render at -o (a folder warpavatar-render did "
                             "not write is refused even so; a video file is always replaced)")
    camera = parser.add_mutually_exclusive_group()
    camera.add_argument("--camera", type=Path, default=None, help="cameras.json to render through")
    camera.add_argument("--orbit", action="store_true",
                        help="circle the avatar once (360 degrees about its up axis) over the animation, starting at "
                             "the training camera: the first camera of --motion's video folder, else the position "
                             "of the fit's training camera (kept in the avatar), looking at the skeleton's centre")
    parser.add_argument("--pose", type=_pose_choice, default=None, metavar="rest|FRAME_ID",
                        help="with --orbit: a turntable of one fixed pose, the rest pose ('rest') or the motion's "
                             "frame with that frame id, over as many video frames as the motion has (--frames "
                             "selects them; default: the avatar follows the motion)")
    parser.add_argument("--size", type=int, default=512,
                        help="orbit image size in pixels: width and height, or the larger side of the training "
                             "camera's image when the orbit starts at one (default 512)")
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
    if args.pose is not None and not args.orbit:
        raise ValueError(f"--pose {args.pose} is a turntable and needs --orbit")
    if not all(0.0 <= value <= 1.0 for value in args.background):
        raise ValueError(f"--background must be R G B in 0..1, got {' '.join(map(str, args.background))}")
    with output_lock(args.output, flag="-o"):
        if not to_video:
            check_replaceable_folder(args.output, kind=FRAMES_KIND, overwrite=args.overwrite, name=f"-o {args.output}")
        return render(args, to_video=to_video)


def _pose_choice(text: str) -> str | int:
    """``--pose``: ``"rest"`` or a frame id (an integer)."""
    if text == "rest":
        return text
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected 'rest' or a frame id (an integer), got {text!r}") from None


def fixed_pose(avatar, motion, pose: str | int, *, motion_path: Path) -> np.ndarray:
    """The bone transforms [J,4,4] of ``--pose``: the identity for ``"rest"``, else the motion's row whose frame id
    is ``pose``.

    Raises:
        ValueError: the motion has no frame with that id (the message names the motion and its ids' range).
    """
    if pose == "rest":
        return np.tile(np.eye(4, dtype=np.float32), (avatar.skeleton.joint_count, 1, 1))
    rows = np.flatnonzero(np.asarray(motion.frame_ids) == pose)
    if rows.size == 0:
        ids = np.asarray(motion.frame_ids)
        raise ValueError(f"--pose {pose}: {motion_path} has no frame with that id (its frame ids run from {ids.min()} "
                         f"to {ids.max()}; --frames selects among them)")
    return np.asarray(motion.bone_transforms[rows[0]], dtype=np.float32)


def orbit_start(avatar, args, frames) -> object | None:
    """The camera ``--orbit`` starts at: the first camera of ``--motion``'s video folder (of the frames
    selected), resized so its larger side is ``--size``; else a camera at the avatar's training camera centre
    (``shading_origin``) looking at the skeleton's centre; None when the avatar keeps no such centre."""
    from warpavatar.io.animation import camera_looking_at_skeleton

    if args.motion.is_dir():
        from warpavatar.data import load_video_folder

        cameras = load_video_folder(args.motion).cameras
        camera = (cameras[frames] if frames is not None else cameras)[0]
        scale = args.size / max(camera.width, camera.height)
        return camera.resized(max(1, round(camera.width * scale)), max(1, round(camera.height * scale)))
    if avatar.shading_origin is not None:
        return camera_looking_at_skeleton(avatar.skeleton, avatar.shading_origin.cpu().numpy(), width=args.size,
                                          height=args.size)
    return None


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
        start = orbit_start(avatar, args, frames) if args.orbit else None
        cameras = orbit_cameras(avatar.skeleton, count, width=args.size, height=args.size, start=start)
    # rows of a motion that keeps every k-th frame of its clock lie k frames apart: the video plays them at
    # fps / k, so the motion keeps its captured speed (as the USD export's time codes do)
    codes = motion_time_codes(motion.frame_ids[:count])
    row_step = float(codes[-1] - codes[0]) / (count - 1) if count > 1 else 1.0
    fps = args.fps or motion.fps / max(row_step, 1.0)
    if args.pose is not None:  # a turntable: the one pose in every frame (consecutive frames of a still body)
        pose = fixed_pose(avatar, motion, args.pose, motion_path=args.motion)
        motion = dataclasses.replace(motion, bone_transforms=np.repeat(pose[None], count, axis=0),
                                     frame_ids=np.arange(count, dtype=np.int32))
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
    """Encode ``frames`` (8-bit RGB images of one size) as the H.264 video ``output`` (yuv420p, through the ffmpeg
    that imageio-ffmpeg ships), through a temporary file that is read back and renamed once complete.

    Browsers, chat clients and README renderers play H.264 in yuv420p, which needs an even width and height: an
    odd side is padded by one pixel (a copy of the last row or column). An ``.mp4`` or ``.mov`` keeps its index at
    the start of the file (``+faststart``), so a web page plays it while it loads.

    Returns:
        the number of frames the finished file holds.

    Raises:
        OSError: ffmpeg cannot write the file, or the file it finished does not hold every frame (a full disk:
            :class:`~warpavatar.io.output_files.DiskFullError`); nothing is left at ``output`` or beside it.
    """
    import imageio_ffmpeg

    from warpavatar.io.images import check_opencv_path

    check_opencv_path(output, "-o")  # OpenCV reads the file back: a path that is not UTF-8 crashes it
    options = ["-crf", str(VIDEO_CRF), "-preset", "medium"]
    if output.suffix.lower() in (".mp4", ".mov"):
        options += ["-movflags", "+faststart"]
    encoder = None
    try:
        with atomic_path(output, suffix=output.suffix) as temporary:
            count = 0
            for pixels in frames:  # (errors of the renderer itself pass through as they are)
                pixels = even_sized(pixels)
                with _encoder_errors(output):
                    if encoder is None:
                        encoder = imageio_ffmpeg.write_frames(
                            str(temporary), (pixels.shape[1], pixels.shape[0]), fps=fps, codec="libx264",
                            pix_fmt_in="rgb24", pix_fmt_out="yuv420p", quality=None, macro_block_size=1,
                            ffmpeg_log_level="quiet", output_params=options)  # ffmpeg's log stays off the terminal
                        encoder.send(None)  # starts ffmpeg
                        size = pixels.shape
                    if pixels.shape != size:
                        raise ValueError(f"{output}: frame {count} is {pixels.shape[1]}x{pixels.shape[0]} pixels, "
                                         f"the video's first frame {size[1]}x{size[0]}; a video holds one size")
                    encoder.send(np.ascontiguousarray(pixels))
                count += 1
            if encoder is not None:
                with _encoder_errors(output):
                    encoder.close()  # waits for ffmpeg to finish the file
                encoder = None
            written = _video_frame_count(temporary)
            if written != count and _nearly_full(output.parent):
                raise disk_full_error(output)
            if written != count:
                raise OSError(f"{output}: ffmpeg finished a video of {written} of its {count} frames; nothing was "
                              "written")
    finally:
        if encoder is not None:
            try:
                encoder.close()
            except Exception:  # noqa: BLE001 - the first error is the one reported
                pass
    return written


@contextlib.contextmanager
def _encoder_errors(output: Path):
    """Turn a failure of ffmpeg (its pipe closed, its exit status) into one line naming ``output``: a full disk
    where the disk is nearly full."""
    try:
        yield
    except (OSError, RuntimeError) as error:
        if _nearly_full(output.parent):
            raise disk_full_error(output) from None
        reason = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        raise OSError(f"{output}: ffmpeg could not write this video ({reason}); nothing was written") from None


def even_sized(pixels: np.ndarray) -> np.ndarray:
    """``pixels`` [H,W,3] uint8 with an odd height or width padded by one row or column (a copy of the last one),
    as yuv420p (its colour planes at half resolution) needs."""
    pad_rows, pad_columns = pixels.shape[0] % 2, pixels.shape[1] % 2
    if not (pad_rows or pad_columns):
        return pixels
    return np.pad(pixels, ((0, pad_rows), (0, pad_columns), (0, 0)), mode="edge")


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
