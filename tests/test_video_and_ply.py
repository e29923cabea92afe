"""warpavatar-render's videos (H.264 that headless Chromium plays, odd sides padded, ffmpeg kept quiet), its
turntable of one pose and an orbit that starts at the training camera, and the .ply without floaters
(warpavatar-animate's export and the fit's canonical.ply)."""

import functools
import http.server
import threading
import time

import cv2
import numpy as np
import pytest
import torch

from conftest import CHROMEDRIVER, CHROMIUM, require_browser, small_avatar
from warpavatar import data
from warpavatar.cli import animate, render
from warpavatar.fit.outputs import FLOATER_LINK, FLOATER_MARGIN, canonical_floaters, write_canonical_ply
from warpavatar.io.animation import orbit_cameras
from warpavatar.io.ply import read_gaussian_ply
from warpavatar.model import Avatar

TRAIN = data.demo_subject_path() / "train"
DANCE = data.demo_subject_path() / "novel_pose" / "dance_cam000"


@pytest.fixture(scope="module")
def skeleton():
    return data.load_video_folder(TRAIN, max_frames=1).skeleton


@pytest.fixture(scope="module")
def avatar_dir(skeleton, tmp_path_factory):
    """A tiny avatar on the demo skeleton (Gaussians around the bones, a briefly distilled field)."""
    avatar = small_avatar(skeleton, seed=3, per_bone=8, cells=8, distill_steps=10)
    folder = tmp_path_factory.mktemp("video_avatar")
    avatar.save(folder / "avatar.pt")
    return folder


def _render(argv, capsys):
    """(exit status, stdout, stderr) of warpavatar-render; argparse's own exits count as a status."""
    try:
        code = render.main([str(argument) for argument in argv] + ["--no-progress", "--device", "cpu"])
    except SystemExit as stop:
        code = stop.code
    out, err = capsys.readouterr()
    return code, out, err


# ------------------------------------------------------------------------------------------------ H.264 video


def test_odd_sides_are_padded_by_a_copy_of_the_last_row_and_column():
    pixels = np.arange(3 * 5 * 3, dtype=np.uint8).reshape(3, 5, 3)
    padded = render.even_sized(pixels)
    assert padded.shape == (4, 6, 3)
    assert np.array_equal(padded[:3, :5], pixels)
    assert np.array_equal(padded[3, :5], pixels[2]) and np.array_equal(padded[:3, 5], pixels[:, 4])
    even = np.zeros((4, 6, 3), np.uint8)
    assert render.even_sized(even) is even


def test_the_video_is_h264_yuv420p_with_even_sides_and_ffmpeg_says_nothing(avatar_dir, tmp_path, capfd):
    video = tmp_path / "orbit.mp4"
    code = render.main([str(avatar_dir), "--motion", str(DANCE), "-o", str(video), "--orbit", "--size", "63",
                        "--frames", "0:4", "--no-progress", "--device", "cpu"])
    out, err = capfd.readouterr()  # the file descriptors: ffmpeg's own output would show here
    assert code == 0 and err == ""
    assert out == f"wrote {video} (4 frames at 10 fps)\n"
    assert sorted(path.name for path in tmp_path.iterdir()) == ["orbit.mp4"]
    head = video.read_bytes()[:64]
    assert head[4:8] == b"ftyp" and b"moov" in video.read_bytes()[:4096]  # +faststart: the index comes first
    capture = cv2.VideoCapture(str(video))
    fourcc = int(capture.get(cv2.CAP_PROP_FOURCC)).to_bytes(4, "little").decode()
    assert fourcc in ("avc1", "h264")
    sizes = []
    while True:
        ok, frame = capture.read()
        if not ok:
            break
        sizes.append(frame.shape[:2])
    assert sizes == [(64, 64)] * 4


PAGE = """<!doctype html><html><body style="background:#000">
<video id="video" src="orbit.mp4" muted playsinline preload="auto"></video>
<canvas id="canvas" width="64" height="64"></canvas>
<script>
window.drawn = null;
const video = document.getElementById("video");
video.addEventListener("error", () => { window.drawn = "error " + (video.error && video.error.message); });
function draw() {
  if (video.readyState < 2) { return null; }
  const context = document.getElementById("canvas").getContext("2d");
  context.drawImage(video, 0, 0, 64, 64);
  return Array.from(context.getImageData(0, 0, 64, 64).data);
}
</script></body></html>
"""


def test_headless_chromium_plays_the_video(avatar_dir, tmp_path):
    require_browser()
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    site = tmp_path / "site"
    site.mkdir()
    assert render.main([str(avatar_dir), "--motion", str(DANCE), "-o", str(site / "orbit.mp4"), "--orbit", "--size",
                        "64", "--frames", "0:3", "--no-progress", "--device", "cpu"]) == 0
    (site / "index.html").write_text(PAGE)
    handler = functools.partial(http.server.SimpleHTTPRequestHandler, directory=str(site))
    handler.log_message = lambda *args: None
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for flag in ("--headless", "--no-sandbox", "--disable-gpu", "--no-first-run", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync", "--disable-dev-shm-usage",
                 "--autoplay-policy=no-user-gesture-required", f"--user-data-dir={tmp_path / 'profile'}"):
        options.add_argument(flag)
    driver = webdriver.Chrome(options=options, service=Service(CHROMEDRIVER))
    try:
        driver.get(f"http://127.0.0.1:{server.server_address[1]}/index.html")
        deadline = time.monotonic() + 30.0
        pixels = None
        while pixels is None and time.monotonic() < deadline:
            failure = driver.execute_script("return window.drawn;")
            assert failure is None, f"Chromium refused the video: {failure}"
            pixels = driver.execute_script("return draw();")
            time.sleep(0.1)
        assert pixels is not None, "the video never reached readyState 2 (HAVE_CURRENT_DATA)"
    finally:
        driver.quit()
        server.shutdown()
        server.server_close()
    rgba = np.asarray(pixels, dtype=np.uint8).reshape(64, 64, 4)
    assert (rgba[..., 3] == 255).all()
    assert (rgba[..., :3].max(-1) > 16).sum() > 20  # the avatar, drawn over the black background


# ------------------------------------------------------------------------------------------------ orbit and turntable


def test_the_orbit_starts_at_the_training_camera_and_turns_about_up(skeleton):
    camera = data.load_video_folder(TRAIN, max_frames=1).cameras[0]
    cameras = orbit_cameras(skeleton, 8, start=camera)
    assert np.abs(cameras[0].world_to_camera - camera.world_to_camera).max() < 1e-5
    assert np.array_equal(cameras[0].K, camera.K.astype(np.float32)) and (cameras[0].width, cameras[0].height) == (
        camera.width, camera.height)
    up = np.asarray(skeleton.up, dtype=np.float64) / np.linalg.norm(skeleton.up)
    centres = np.stack([-c.world_to_camera[:3, :3].T.astype(np.float64) @ c.world_to_camera[:3, 3] for c in cameras])
    assert np.allclose(centres @ up, centres[0] @ up, atol=1e-5)  # the same height all round
    points = np.concatenate([skeleton.heads, skeleton.tails])
    axis_point = 0.5 * (points.min(0) + points.max(0))
    radial = (centres - axis_point) - np.outer((centres - axis_point) @ up, up)
    assert np.allclose(np.linalg.norm(radial, axis=1), np.linalg.norm(radial[0]), atol=1e-5)
    quarter = radial[2] / np.linalg.norm(radial[2])  # 2 of 8 frames: a quarter turn, right-handed about up
    assert np.allclose(quarter, np.cross(up, radial[0] / np.linalg.norm(radial[0])), atol=1e-5)


def test_render_orbits_from_the_motion_folders_first_camera_or_the_training_camera_centre(avatar_dir, skeleton):
    avatar = Avatar.load(avatar_dir)
    args = render.build_parser().parse_args([str(avatar_dir), "--motion", str(TRAIN), "-o", "o.mp4", "--orbit",
                                             "--size", "64"])
    start = render.orbit_start(avatar, args, slice(2, 4))
    first = data.load_video_folder(TRAIN).cameras[2]
    assert np.abs(start.world_to_camera - first.world_to_camera).max() < 1e-5
    assert (start.width, start.height) == (64, 64)  # the 128x128 training camera at --size 64
    assert np.allclose(start.K, first.resized(64, 64).K)
    # a motion without cameras (the training motion's .npz): from the training camera's centre the avatar keeps
    args.motion = avatar_dir / "training_poses.npz"
    assert render.orbit_start(avatar, args, None) is None  # this avatar keeps none: the fixed side of before
    avatar.shading_origin = torch.as_tensor(first.camera_to_world[:3, 3], dtype=torch.float32)
    start = render.orbit_start(avatar, args, None)
    camera = orbit_cameras(skeleton, 4, start=start)[0]
    centre = -camera.world_to_camera[:3, :3].T @ camera.world_to_camera[:3, 3]
    assert np.abs(centre - first.camera_to_world[:3, 3]).max() < 1e-5


class _RecordingPlayer:
    """Stands in for :class:`warpavatar.model.playback.Player`: records the bones of each frame."""

    bones = []

    def __init__(self, avatar, camera, *, background):
        self.size = (int(camera.width), int(camera.height))

    def render(self, bones, *, camera, inputs, frame_index):
        type(self).bones.append(np.asarray(bones.cpu().numpy()))
        image = torch.zeros(self.size[1], self.size[0], 3)
        return image, image[..., 0], image[..., 0]


@pytest.mark.parametrize("pose", ["rest", "12"])
def test_pose_renders_the_same_bones_in_every_frame(avatar_dir, tmp_path, monkeypatch, capsys, pose):
    _RecordingPlayer.bones = []
    monkeypatch.setattr(render, "Player", _RecordingPlayer)
    code, out, err = _render([avatar_dir, "--motion", DANCE, "-o", tmp_path / "frames", "--orbit", "--size", "32",
                              "--pose", pose, "--frames", "0:5"], capsys)
    assert code == 0, err
    assert out == f"wrote {tmp_path / 'frames'} (5 frames at 10 fps)\n"
    assert len(_RecordingPlayer.bones) == 5
    motion = data.load_video_folder(DANCE)
    expected = (np.tile(np.eye(4, dtype=np.float32), (motion.skeleton.joint_count, 1, 1)) if pose == "rest"
                else motion.bone_transforms[list(motion.frame_ids).index(12)])
    for bones in _RecordingPlayer.bones:
        assert np.array_equal(bones, expected)


@pytest.mark.parametrize("options, message", [
    (["--pose", "rest"], "error: --pose rest is a turntable and needs --orbit\n"),
    (["--orbit", "--pose", "still"], "warpavatar-render: error: argument --pose: expected 'rest' or a frame id (an "
                                     "integer), got 'still' (--help explains every option)\n"),
    (["--orbit", "--pose", "1", "--frames", "0:4"], "error: --pose 1: {DANCE} has no frame with that id (its frame "
                                                    "ids run from 0 to 9; --frames selects among them)\n"),
])
def test_pose_errors_are_one_line(avatar_dir, tmp_path, capsys, options, message):
    code, out, err = _render([avatar_dir, "--motion", DANCE, "-o", tmp_path / "frames", *options], capsys)
    assert (code, out) == (2, "")
    assert err == message.format(DANCE=DANCE)
    assert not (tmp_path / "frames").exists()


# ------------------------------------------------------------------------------------------------ .ply floaters


@pytest.fixture(scope="module")
def floater_avatar_dir(skeleton, tmp_path_factory):
    """A tiny avatar with Gaussian 0 moved 2 skeleton heights above the head and Gaussian 1 made transparent."""
    avatar = small_avatar(skeleton, seed=4, per_bone=4, cells=8, distill_steps=5)
    up = np.asarray(skeleton.up, dtype=np.float64) / np.linalg.norm(skeleton.up)
    points = np.concatenate([skeleton.heads, skeleton.tails])
    height = float(np.ptp(points @ up))
    with torch.no_grad():
        avatar.gaussians.means[0] = torch.as_tensor(points[np.argmax(points @ up)] + 2.0 * height * up)
        avatar.gaussians.opacity_logits[1] = -10.0  # opacity 4.5e-5, below 1/255
    folder = tmp_path_factory.mktemp("floater_avatar")
    avatar.save(folder / "avatar.pt")
    return folder


def test_the_floater_rule_drops_far_and_transparent_gaussians(skeleton):
    up = np.asarray(skeleton.up, dtype=np.float64) / np.linalg.norm(skeleton.up)
    points = np.concatenate([skeleton.heads, skeleton.tails]).astype(np.float64)
    height = float(np.ptp(points @ up))
    top = points[np.argmax(points @ up)]
    # just inside the margin, just past it but linked to that one, far past it alone, transparent
    means = torch.as_tensor(np.stack([top, top + (FLOATER_MARGIN - 0.01) * height * up,
                                      top + (FLOATER_MARGIN + 0.01) * height * up,
                                      top + (FLOATER_MARGIN + 0.2) * height * up, top]))
    opacities = torch.tensor([1.0, 1.0, 1.0, 1.0, 0.5 / 255])
    assert canonical_floaters(means, opacities, skeleton).tolist() == [False, False, False, True, True]
    # a chain of close Gaussians (a big head, a long coat) reaches far past the margin and stays; the gap at its
    # end cuts off what lies beyond
    steps = np.arange(0.0, FLOATER_MARGIN + 0.5, 0.5 * FLOATER_LINK)
    chain = np.concatenate([top + steps[:, None] * height * up, [top + (steps[-1] + 0.1) * height * up]])
    floaters = canonical_floaters(torch.as_tensor(chain), torch.ones(len(chain)), skeleton)
    assert not floaters[:-1].any() and floaters[-1]
    # with scales, Gaussians whose 3-sigma bodies touch are linked across a wider gap
    pair = torch.as_tensor(np.stack([top + (FLOATER_MARGIN - 0.01) * height * up,
                                     top + (FLOATER_MARGIN + 0.09) * height * up]))
    assert canonical_floaters(pair, torch.ones(2), skeleton).tolist() == [False, True]
    wide = torch.full((2, 3), 1.2 * 0.1 * height / 6.0, dtype=torch.float64)  # 3 sigma each: 0.06 h, together 0.12 h
    assert canonical_floaters(pair, torch.ones(2), skeleton, scales=wide).tolist() == [False, False]


def test_ply_export_leaves_floaters_out_and_keep_floaters_keeps_them(floater_avatar_dir, tmp_path, capsys):
    avatar = Avatar.load(floater_avatar_dir)
    count = avatar.gaussians.count
    for options, kept in (([], count - 2), (["--keep-floaters"], count)):
        output = tmp_path / f"rest{len(options)}.ply"
        code = animate.main([str(floater_avatar_dir), "-o", str(output), "--no-progress", "--device", "cpu", *options])
        out, err = capsys.readouterr()
        assert code == 0, err
        left_out = ", 2 floaters left out (--keep-floaters keeps them)" if not options else ""
        assert out.startswith(f"wrote {output} (3DGS .ply of the rest pose, {kept} Gaussians{left_out}, ")
        means = read_gaussian_ply(output)["means"]
        expected = avatar.gaussians.means.detach().numpy()[2:] if not options else avatar.gaussians.means.detach()
        assert np.array_equal(means, np.asarray(expected))
    # the fit writes canonical.ply with the same rule: byte for byte the export
    write_canonical_ply(avatar.gaussians, tmp_path / "canonical.ply", skeleton=avatar.skeleton)
    assert (tmp_path / "canonical.ply").read_bytes() == (tmp_path / "rest0.ply").read_bytes()
    assert Avatar.load(floater_avatar_dir).gaussians.count == count  # the avatar file keeps every Gaussian


def test_keep_floaters_is_refused_for_formats_that_write_every_gaussian(floater_avatar_dir, tmp_path, capsys):
    output = tmp_path / "dance.usdc"
    code = animate.main([str(floater_avatar_dir), "-o", str(output), "--keep-floaters", "--motion", str(DANCE)])
    out, err = capsys.readouterr()
    assert (code, out) == (2, "")
    assert err == (f"error: -o {output}: the usd-particlefield format writes every Gaussian, so --keep-floaters "
                   "would not be used; leave it out\n")
    assert list(tmp_path.iterdir()) == []
