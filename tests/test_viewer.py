"""warpavatar-view: the camera conversion, the skeleton's segments, the command's errors, what it accepts from a
browser (the websocket's origin, the render size), and the page in a real browser (Debian's Chromium, headless,
driven by Selenium through chromedriver; skipped where either is missing, unless CI is set)."""

import math
import shutil
import sys
import tempfile
import time
import types

import cv2
import numpy as np
import pytest
import torch

from conftest import CHROMEDRIVER, CHROMIUM, require_browser, small_avatar
from warpavatar import data
from warpavatar.cli import view
from warpavatar.fit.outputs import TRAINING_MOTION_NAME, write_training_motion
from warpavatar.geometry import quat_from_matrix
from warpavatar.io.animation import orbit_cameras
from warpavatar.io.motion import load_motion
from warpavatar.io.viewer import (MAX_RENDER_PIXELS, MAX_RENDER_SIDE, RENDERING_TEXT, opencv_camera, origin_refusal,
                                  render_size, skeleton_segments)



@pytest.fixture(scope="module")
def avatar_dir(tmp_path_factory):
    """A small avatar on the demo skeleton, saved with a training motion of 6 demo frames beside it (as a fit
    leaves them)."""
    video = data.load_video_folder(data.demo_subject_path() / "train", max_frames=6)
    torch.manual_seed(0)
    avatar = small_avatar(video.skeleton, seed=5, per_bone=24, cells=12, distill_steps=30)
    folder = tmp_path_factory.mktemp("view_avatar")
    avatar.save(folder / "avatar.pt")
    frames = types.SimpleNamespace(bone_transforms=torch.as_tensor(video.bone_transforms),
                                   frame_ids=video.frame_ids, video=video)
    write_training_motion(frames, folder / TRAINING_MOTION_NAME)
    return folder


def test_training_motion_reads_back_as_a_motion(avatar_dir):
    video = data.load_video_folder(data.demo_subject_path() / "train", max_frames=6)
    motion = load_motion(avatar_dir / TRAINING_MOTION_NAME, video.skeleton)
    np.testing.assert_array_equal(motion.bone_transforms, video.bone_transforms)
    np.testing.assert_array_equal(motion.frame_ids, video.frame_ids)
    assert motion.fps == video.fps
    assert not list(avatar_dir.glob("*.tmp"))


def test_opencv_camera_inverts_the_browser_pose():
    """A camera given as viser gives it (camera-to-world rotation, centre, vertical fov) comes back as the OpenCV
    camera it was made from, at any image height."""
    skeleton = data.load_video_folder(data.demo_subject_path() / "train", max_frames=2).skeleton
    for reference in orbit_cameras(skeleton, 5, width=300, height=200, field_of_view_degrees=50.0):
        rotation = reference.world_to_camera[:3, :3].astype(np.float64)
        centre = -rotation.T @ reference.world_to_camera[:3, 3]
        fov = 2 * math.atan(0.5 * 200 / reference.K[1, 1])
        camera = opencv_camera(quat_from_matrix(rotation.T), centre, fov, height=200, aspect=1.5)
        assert (camera.width, camera.height) == (300, 200)
        np.testing.assert_allclose(camera.world_to_camera, reference.world_to_camera, atol=1e-5)
        np.testing.assert_allclose(camera.K, reference.K, rtol=1e-5)
        half = opencv_camera(quat_from_matrix(rotation.T), centre, fov, height=100, aspect=1.5)
        np.testing.assert_allclose(half.K[:2, :2], reference.K[:2, :2] / 2, rtol=1e-5)
        assert (half.K[0, 2], half.K[1, 2]) == (74.5, 49.5)  # pixel centres at integer coordinates
    with pytest.raises(ValueError, match="field of view"):
        opencv_camera((1, 0, 0, 0), (0, 0, 0), 0.0, height=10, aspect=1.0)


def test_skeleton_segments_follow_the_pose_and_mark_grown_joints():
    skeleton = data.Skeleton(names=["root", "arm", "grown_root_0"], parents=[-1, 0, 0],
                             heads=[[0, 0, 0], [0, 0, 1], [0.2, 0, 0.5]], tails=[[0, 0, 1], [0, 0, 2], [0.3, 0, 0.5]])
    transforms = np.tile(np.eye(4), (3, 1, 1))
    transforms[:, :3, 3] = [1.0, 2.0, 3.0]
    points, grown = skeleton_segments(skeleton, transforms, joint_count=2)
    # three bones, then a link from the root's head to the grown joint, which does not start at the root's tail
    np.testing.assert_allclose(points[:3, 0], skeleton.heads + [1, 2, 3])
    np.testing.assert_allclose(points[:3, 1], skeleton.tails + [1, 2, 3])
    np.testing.assert_allclose(points[3], [[1, 2, 3], [1.2, 2, 3.5]])
    assert grown.tolist() == [False, False, True, True]


def test_help_explains_the_options(capsys):
    with pytest.raises(SystemExit):
        view.main(["--help"])
    text = " ".join(capsys.readouterr().out.split())
    for expected in ("--port", "default 8080", "--host", "default 127.0.0.1", "--image-size", "pixels",
                     "training_poses.npz", "--device", "--skeleton", "--play", "pip install",
                     "Only the viewer's own page may connect", "Renders are capped at 4096 pixels a side and "
                     "8,388,608 pixels in all (64 bytes a pixel within 512 MiB"):
        assert expected in text, expected


def test_view_without_viser_says_how_to_install(avatar_dir, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "viser", None)  # import viser raises ImportError
    assert view.main([str(avatar_dir), "--device", "cpu"]) == 2
    error = capsys.readouterr().err.strip()
    assert len(error.splitlines()) == 1 and "pip install" in error and "viser" in error


def test_view_bad_input_is_a_clear_error(avatar_dir, tmp_path, capsys):
    pytest.importorskip("viser")
    assert view.main([str(tmp_path / "nothing"), "--device", "cpu"]) == 2
    assert "no avatar file" in capsys.readouterr().err
    assert view.main([str(avatar_dir), "--image-size", "0", "--device", "cpu"]) == 2
    assert "--image-size" in capsys.readouterr().err


def test_render_size_is_capped_a_side_and_in_pixels_keeping_the_aspect():
    assert (MAX_RENDER_SIDE, MAX_RENDER_PIXELS) == (4096, 8_388_608)
    assert render_size(1000, 500, rows=256) == (512, 256)  # the slider's rows at the canvas's aspect
    assert render_size(1000, 100, rows=256) == (1000, 100)  # never more rows than the canvas
    assert render_size(3840, 2160, rows=2160) == (3840, 2160)  # 4K UHD fits
    assert render_size(10**6, 2000, rows=2000) == (4096, 8)  # a side capped, the aspect kept
    assert render_size(4096, 4096, rows=4096) == (2896, 2896)  # capped by the pixels: 2896**2 <= 2**23
    assert render_size(10**9, 10**9, rows=10**9) == (2896, 2896)
    for bad in (0, -5, float("nan"), float("inf"), "text", None):
        assert render_size(bad, bad, rows=bad) == (1, 1)
    width, height = render_size(2**31, 3, rows=2**31)
    assert width <= MAX_RENDER_SIDE and height >= 1 and width * height <= MAX_RENDER_PIXELS


@pytest.mark.parametrize("origin,host,listen,refusal", [
    ("http://127.0.0.1:8080", "127.0.0.1:8080", "127.0.0.1", None),
    ("http://localhost:8080", "localhost:8080", "127.0.0.1", None),
    ("http://[::1]:8080", "[::1]:8080", "::1", None),
    ("http://localhost", "localhost", "127.0.0.1", None),  # port 80, named by neither header
    ("http://192.168.1.5:8080", "192.168.1.5:8080", "0.0.0.0", None),  # --host 0.0.0.0, reached by its address
    ("http://workstation:8080", "workstation:8080", "workstation", None),  # the --host name itself
    ("https://evil.example", "127.0.0.1:8080", "127.0.0.1", "Origin 'https://evil.example' is another site than the "
                                                            "viewer (127.0.0.1:8080)"),
    ("http://127.0.0.1:8081", "127.0.0.1:8080", "127.0.0.1", "Origin 'http://127.0.0.1:8081' is another site than "
                                                             "the viewer (127.0.0.1:8080)"),
    ("http://localhost:8080", "127.0.0.1:8080", "127.0.0.1", "Origin 'http://localhost:8080' is another site than "
                                                             "the viewer (127.0.0.1:8080)"),
    ("http://rebound.example:8080", "rebound.example:8080", "127.0.0.1",
     "Origin 'http://rebound.example:8080' names this machine by 'rebound.example', which a web page could point "
     "elsewhere; open the viewer at localhost, an IP address or the --host name"),
    (None, "127.0.0.1:8080", "127.0.0.1", "no Origin header (only the viewer's own page may connect)"),
    ("null", "127.0.0.1:8080", "127.0.0.1", "Origin 'null' is not a web page's origin"),
    ("file://", "127.0.0.1:8080", "127.0.0.1", "Origin 'file://' is not a web page's origin"),
    ("http://127.0.0.1:8080", None, "127.0.0.1", "no usable Host header (got None)"),
])
def test_origin_refusal_accepts_only_the_viewers_own_page(origin, host, listen, refusal):
    assert origin_refusal(origin, host, listen_host=listen) == refusal


@pytest.fixture
def live_viewer(avatar_dir):
    pytest.importorskip("viser")
    viewer = view.build_viewer(view.build_parser().parse_args([str(avatar_dir), "--port", "0", "--device", "cpu",
                                                               "--no-progress", "--image-size", "64"]))
    yield viewer
    viewer.stop()


def _websocket(viewer, origin):
    """A websocket to the viewer as viser's page opens it, with the given Origin header (None: none)."""
    import viser
    from websockets.sync.client import connect

    return connect(f"ws://127.0.0.1:{viewer.server.get_port()}", subprotocols=[f"viser-v{viser.__version__}"],
                   open_timeout=10, **({} if origin is None else {"origin": origin}))


def _first_message(websocket):
    """The first message the server sends, or the close code it sends instead."""
    from websockets.exceptions import ConnectionClosed

    try:
        return websocket.recv(timeout=10)
    except ConnectionClosed as closed:
        return closed.rcvd.code if closed.rcvd is not None else None


def test_the_viewer_refuses_websockets_from_other_pages(live_viewer, capsys):
    port = live_viewer.server.get_port()
    for origin in ("http://evil.example", f"http://127.0.0.1:{port + 1}", None):
        with _websocket(live_viewer, origin) as websocket:
            assert _first_message(websocket) == 1008, origin  # closed before anything was sent
    assert live_viewer.refused_connections == 3
    assert capsys.readouterr().err.splitlines() == [
        "warpavatar-view: refused a connection: Origin 'http://evil.example' is another site than the viewer "
        f"(127.0.0.1:{port})",
        f"warpavatar-view: refused a connection: Origin 'http://127.0.0.1:{port + 1}' is another site than the viewer "
        f"(127.0.0.1:{port})",
        "warpavatar-view: refused a connection: no Origin header (only the viewer's own page may connect)"]
    with _websocket(live_viewer, f"http://127.0.0.1:{port}") as websocket:  # the viewer's own page
        assert isinstance(_first_message(websocket), bytes)
    assert live_viewer.refused_connections == 3


def test_the_viewer_caps_the_render_size_a_browser_asks_for(live_viewer):
    import msgspec
    from viser import _messages

    port = live_viewer.server.get_port()
    with _websocket(live_viewer, f"http://127.0.0.1:{port}") as websocket:
        # a page that has no image yet says so (and shows the background colour rather than white)
        _wait(lambda: live_viewer.stats_text.content == RENDERING_TEXT, "the rendering message")
        for width, height in ((10**7, 4000), (64, 64)):
            count = live_viewer.render_count
            camera = _messages.ViewerCameraMessage(
                wxyz=(1.0, 0.0, 0.0, 0.0), position=(0.0, 0.0, -3.0), fov=0.7, near=0.01, far=100.0,
                image_height=height, image_width=width, look_at=(0.0, 0.0, 0.0), up_direction=(0.0, -1.0, 0.0))
            websocket.send(msgspec.msgpack.encode(camera.as_serializable_dict()))
            _wait(lambda: live_viewer.render_count > count, "a render")
            # at most the resolution slider's 64 rows, then capped to 4096 a side keeping the canvas's aspect
            assert live_viewer.last_image.shape == ((1, 4096, 3) if width > height else (64, 64, 3))
    assert live_viewer.last_error is None
    assert live_viewer.stats_text.content.startswith("64x64 pixels, ")  # the message gave way to the render's


def test_view_plays_the_given_motion_or_the_rest_pose(avatar_dir, tmp_path, capsys):
    pytest.importorskip("viser")
    motion_folder = data.demo_subject_path() / "novel_pose" / "dance_cam000"
    args = view.build_parser().parse_args([str(avatar_dir / "avatar.pt"), "--motion", str(motion_folder), "--frames",
                                           "2:5", "--port", "0", "--device", "cpu", "--no-progress"])
    viewer = view.build_viewer(args)
    try:
        assert viewer.frame_count == 3 and viewer.motion.frame_ids.tolist() == \
            data.load_video_folder(motion_folder).frame_ids[2:5].tolist()
        assert viewer.url.startswith("http://127.0.0.1:") and viewer.url.split(":")[-1] != "0/"
    finally:
        viewer.stop()
    # an avatar without a training motion beside it (a fit older than the viewer) shows its rest pose
    shutil.copy(avatar_dir / "avatar.pt", tmp_path / "avatar.pt")
    viewer = view.build_viewer(view.build_parser().parse_args([str(tmp_path), "--port", "0", "--device", "cpu"]))
    try:
        assert viewer.frame_count == 1
        np.testing.assert_array_equal(viewer.motion.bone_transforms[0], np.tile(np.eye(4), (viewer.avatar.joint_count, 1, 1)))
        assert "rest pose" in capsys.readouterr().out
    finally:
        viewer.stop()


# ------------------------------------------------------------------------------------------------ the browser
def _browser(user_data_dir):
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for flag in ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync",
                 "--disable-dev-shm-usage", "--enable-unsafe-swiftshader", "--window-size=1000,700", "--force-device-scale-factor=1",
                 f"--user-data-dir={user_data_dir}"):
        options.add_argument(flag)
    return webdriver.Chrome(options=options, service=Service(CHROMEDRIVER))


def _canvas_strip(driver):
    """The screenshot's central third of the 3D canvas (clear of the panel and notifications), RGB, and the
    canvas size in pixels."""
    canvas = max(driver.find_elements("tag name", "canvas"), key=lambda c: c.rect["width"] * c.rect["height"])
    rect = canvas.rect
    shot = cv2.imdecode(np.frombuffer(driver.get_screenshot_as_png(), np.uint8), cv2.IMREAD_COLOR)[..., ::-1]
    x, y, width, height = (int(round(rect[k])) for k in ("x", "y", "width", "height"))
    shot = shot[y:y + height, x:x + width]
    return shot[:, width // 3: 2 * width // 3].astype(np.float32), (width, height)


def _server_strip(image, size):
    width, height = size
    resized = cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA)
    return resized[:, width // 3: 2 * width // 3].astype(np.float32)


def _wait(condition, what, timeout=20.0):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if condition():
            return
        time.sleep(0.1)
    raise AssertionError(f"timed out waiting for {what}")


def _settled_screen(driver, viewer):
    """Wait until the server has sent nothing new for 0.6 s and the page shows its last image; returns the
    screenshot's strip and the server's image's strip."""
    deadline = time.monotonic() + 20.0
    while True:
        count = viewer.render_count
        time.sleep(0.6)
        if viewer.render_count == count:
            break
        assert time.monotonic() < deadline, "renders did not settle"
    expected = viewer.last_image
    while True:  # the page draws the image a moment after it arrives
        strip, size = _canvas_strip(driver)
        server = _server_strip(expected, size)
        if np.abs(strip - server).mean() < 6.0 or time.monotonic() > deadline:
            return strip, server
        time.sleep(0.2)


def test_the_page_shows_the_avatar_and_follows_camera_and_timeline(avatar_dir, tmp_path):
    require_browser()
    from selenium.webdriver.common.action_chains import ActionChains

    args = view.build_parser().parse_args([str(avatar_dir), "--port", "0", "--device", "cpu", "--image-size",
                                           "256", "--fps", "2", "--no-progress", "--background", "0.1", "0.1", "0.1"])
    viewer = view.build_viewer(args)
    driver = None
    try:
        assert viewer.frame_count == 6  # the training motion beside the avatar
        driver = _browser(tempfile.mkdtemp(dir=tmp_path))
        driver.set_page_load_timeout(30)
        driver.get(viewer.url)
        _wait(lambda: viewer.render_count > 0, "the first render")
        first, server = _settled_screen(driver, viewer)
        # the avatar, not a blank page: enough pixels away from the background, and the page shows the image
        # the server rendered
        assert (np.abs(server - 25.5).max(axis=-1) > 40).mean() > 0.01
        assert (np.abs(first - 25.5).max(axis=-1) > 40).mean() > 0.01
        assert np.abs(first - server).mean() < 6.0, np.abs(first - server).mean()
        assert viewer.last_image.shape[0] == 256
        # everything the page loaded came from the viewer itself (viser's client is in its wheel)
        host = viewer.url.rstrip("/")
        loaded = driver.execute_script("return performance.getEntriesByType('resource').map(e => e.name)")
        assert all(url.startswith((host, "data:", "blob:")) for url in loaded), loaded

        # orbit: drag across the canvas; the server renders the new view and the page shows it
        canvas = max(driver.find_elements("tag name", "canvas"), key=lambda c: c.rect["width"])
        count = viewer.render_count
        ActionChains(driver).move_to_element_with_offset(canvas, -100, 60).click_and_hold() \
            .move_by_offset(60, 0).move_by_offset(60, 0).move_by_offset(60, 0).release().perform()
        _wait(lambda: viewer.render_count > count, "a render for the moved camera")
        orbited, server = _settled_screen(driver, viewer)
        assert np.abs(orbited - server).mean() < 6.0
        assert np.abs(orbited - first).mean() > 2.0, np.abs(orbited - first).mean()

        # the timeline: press Play in the page and the motion runs (2 frames per second); press Pause and it stays
        driver.find_element("xpath", "//button[normalize-space()='Play']").click()
        _wait(lambda: viewer.frame >= 2, "playback to reach frame 2")
        driver.find_element("xpath", "//button[normalize-space()='Pause']").click()
        paused, server = _settled_screen(driver, viewer)
        frame = viewer.frame
        time.sleep(1.0)
        assert viewer.frame == frame == int(viewer.frame_slider.value)
        assert np.abs(paused - server).mean() < 6.0

        # a frame chosen on the timeline shows that frame; back at frame 0 the page shows what it showed there
        viewer.set_frame(3)
        _wait(lambda: viewer.frame == 3, "frame 3")
        third, server = _settled_screen(driver, viewer)
        assert np.abs(third - server).mean() < 6.0
        assert np.abs(third - orbited).mean() > 2.0, np.abs(third - orbited).mean()
        viewer.set_frame(0)
        _wait(lambda: viewer.frame == 0, "frame 0")
        back, server = _settled_screen(driver, viewer)
        assert np.abs(back - server).mean() < 6.0
        assert np.abs(back - orbited).mean() < 6.0  # the same camera and frame as before playing

        # the skeleton, drawn by the page over the server's image
        shown = [box for box in driver.find_elements("xpath", "//input[@type='checkbox']") if box.rect["width"] > 0]
        assert len(shown) == 1, "the panel shows one checkbox, the skeleton's"
        shown[0].click()
        _wait(lambda: viewer.skeleton_box.value, "the skeleton checkbox")
        time.sleep(0.5)
        with_skeleton, _ = _canvas_strip(driver)
        assert np.abs(with_skeleton - back).max(axis=-1).__gt__(60).sum() > 50
    finally:
        if driver is not None:
            driver.quit()
        viewer.stop()
