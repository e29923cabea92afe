"""``warpavatar-view``: look at a fitted avatar in a web browser, orbiting it and scrubbing through a motion."""

from __future__ import annotations

import sys

import numpy as np
import torch

from warpavatar.cli.common import avatar_parser, friendly_errors, load_avatar, load_motion_for

DESCRIPTION = """Serve a web page that shows a fitted avatar, rendered on this machine (CPU or CUDA) with the avatar's
own rasterizer as you move the camera: drag to orbit, scroll to zoom, right-drag to pan. The panel has a
timeline of the motion (frame index), play/pause, the playback rate, the skeleton (grown joints in orange) and
the render resolution (--fps sets the playback rate at start). Open the printed address in a browser;
Ctrl+C stops the server.

Needs viser: pip install "warpavatar[view]" (or pip install viser). Its page is served from the installed
package; nothing is fetched from the internet. To look from another machine, forward the port
(ssh -L 8080:localhost:8080 host) or listen on every interface (--host 0.0.0.0).

Only the viewer's own page may connect: a websocket whose Origin is another site (any other web page open in the
browser) is refused, and so is one reaching this machine by a name other than localhost, an IP address or the
--host name. Renders are capped at {side} pixels a side and {pixels:,} pixels in all ({per_pixel} bytes a pixel
within {budget} MiB; 4K UHD fits): a larger request is scaled down, keeping its aspect.
"""

TRAINING_MOTION_HELP = "the fit's training motion, training_poses.npz in the fit's output folder; the rest pose " \
                       "where the folder has none"


def _description() -> str:
    from warpavatar.io.viewer import MAX_RENDER_PIXELS, MAX_RENDER_SIDE, RENDER_BYTES_PER_PIXEL, RENDER_MEMORY_BUDGET

    return DESCRIPTION.format(side=MAX_RENDER_SIDE, pixels=MAX_RENDER_PIXELS, per_pixel=RENDER_BYTES_PER_PIXEL,
                              budget=RENDER_MEMORY_BUDGET // 2**20)


def build_parser():
    parser = avatar_parser("warpavatar-view", _description(), motion=True, motion_default=TRAINING_MOTION_HELP)
    parser.add_argument("--port", type=int, default=8080,
                        help="TCP port of the page (default 8080; 0: any free port; a busy port moves on to the next "
                             "free one, and the address printed says which)")
    parser.add_argument("--host", default="127.0.0.1",
                        help="network address to listen on (default 127.0.0.1: this machine only; 0.0.0.0: every "
                             "interface)")
    parser.add_argument("--image-size", type=int, default=512, metavar="PIXELS",
                        help="height of the rendered images in pixels at start, at most the browser window's; the "
                             "width follows the window's aspect (default 512, at most 4096; the page's 'resolution' "
                             "slider changes it)")
    parser.add_argument("--background", type=float, nargs=3, default=(0.0, 0.0, 0.0), metavar=("R", "G", "B"),
                        help="background colour of the renders in 0..1 (default black)")
    parser.add_argument("--skeleton", action="store_true", help="show the skeleton at start (default: hidden)")
    parser.add_argument("--play", action="store_true", help="start playing the motion (default: paused at frame 0)")
    return parser


def _missing_viser() -> bool:
    try:
        import viser  # noqa: F401
    except ImportError:
        return True
    return False


def rest_motion(avatar):
    """A one-frame motion holding the avatar's rest pose."""
    from warpavatar.io.motion import Motion

    bones = np.tile(np.eye(4, dtype=np.float32), (1, avatar.joint_count, 1, 1))
    return Motion(bone_transforms=bones, fps=30.0, frame_ids=np.zeros(1, dtype=np.int32))


def build_viewer(args):
    """The :class:`~warpavatar.io.viewer.AvatarViewer` that ``args`` (of :func:`build_parser`) ask for, serving."""
    from warpavatar.fit.outputs import TRAINING_MOTION_NAME
    from warpavatar.io.viewer import MAX_RENDER_SIDE, AvatarViewer

    if not 1 <= args.image_size <= MAX_RENDER_SIDE:
        raise ValueError(f"--image-size must be between 1 and {MAX_RENDER_SIDE} pixels, got {args.image_size}")
    if not 0 <= args.port <= 65535:
        raise ValueError(f"--port must be between 0 and 65535, got {args.port}")
    avatar = load_avatar(args)
    if args.motion is None:
        folder = args.avatar if args.avatar.is_dir() else args.avatar.parent
        if (folder / TRAINING_MOTION_NAME).is_file():
            args.motion = folder / TRAINING_MOTION_NAME
    if args.motion is None:
        print(f"{folder / TRAINING_MOTION_NAME} does not exist (a fit older than this version): showing the rest "
              f"pose; give --motion to play a motion")
        motion, part_inputs = rest_motion(avatar), {}
    else:
        motion, _, part_inputs = load_motion_for(avatar, args)
    return AvatarViewer(avatar, motion, part_inputs=part_inputs, host=args.host, port=args.port,
                        image_height=args.image_size, background=args.background, fps=args.fps,
                        show_skeleton=args.skeleton, play=args.play, progress=not args.no_progress)


@friendly_errors
@torch.no_grad()
def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if _missing_viser():
        print('error: warpavatar-view needs viser: pip install "warpavatar[view]" (or pip install viser)',
              file=sys.stderr)
        return 2
    viewer = build_viewer(args)
    print(f"warpavatar-view: {viewer.frame_count} frames on {viewer.device}; open {viewer.url} (Ctrl+C stops)",
          flush=True)
    try:
        viewer.serve_forever()
    except KeyboardInterrupt:
        pass
    return 0


if __name__ == "__main__":
    sys.exit(main())
