"""An interactive web viewer of a fitted avatar (``warpavatar-view``).

`viser <https://viser.studio>`_ serves the page (its client ships inside the wheel: nothing is fetched from the
network) and reports each browser's camera; the server poses the avatar with the same code path as fitting,
evaluation and the exporters (:meth:`warpavatar.model.Avatar.pose`, every part included), renders it with the
avatar's own rasterizer at that camera and sends the image as the page's background. It renders again when the
camera, the frame, the resolution or the background changes, never faster than renders complete (the newest
state wins), and plays the motion at its frame rate by skipping frames where rendering is slower.

The page has a timeline (frame index), play/pause, the playback rate, the skeleton (line segments between the
posed joints, the joints grown by ``--grow-joints`` in another colour) and the render resolution.

What a browser sends is not trusted: only pages loaded from the viewer itself may open its websocket
(:func:`origin_refusal`; any other web page the user has open could otherwise watch the renders and drive the
controls), and the size of a render is capped (:func:`render_size`) whatever size the page asks for.
"""

from __future__ import annotations

import asyncio
import ipaddress
import math
import sys
import threading
import time
import urllib.parse

import numpy as np
import torch

from warpavatar.geometry import quat_to_matrix
from warpavatar.io.animation import OrbitCamera, orbit_cameras

__all__ = ["MAX_RENDER_SIDE", "RENDER_BYTES_PER_PIXEL", "RENDER_MEMORY_BUDGET", "MAX_RENDER_PIXELS", "render_size",
           "origin_refusal", "opencv_camera", "skeleton_segments", "AvatarViewer"]

RENDERING_TEXT = "rendering..."
"""What the panel says until a browser's first image is rendered."""

MAX_RENDER_SIDE = 4096
"""The widest and the tallest image the viewer renders [pixels], whatever a browser asks for."""

RENDER_BYTES_PER_PIXEL = 64
"""Memory one rendered pixel costs the server [bytes], rounded up: the rasterizer's per-pixel outputs and state
(28 B, docs/rasterizer_memory.md) and the copies that turn its float image into a JPEG; measured on the CPU as
about 40 B (peak resident memory of a 2048 x 2048 render)."""

RENDER_MEMORY_BUDGET = 512 * 2**20
"""The most memory [bytes] one render's pixels may take: ``width * height * RENDER_BYTES_PER_PIXEL`` stays within
it."""

MAX_RENDER_PIXELS = RENDER_MEMORY_BUDGET // RENDER_BYTES_PER_PIXEL
"""The most pixels of one render, 8,388,608 (4K UHD, 3840 x 2160, fits; 4096 x 4096 does not)."""

_SKELETON_COLOUR = (0.10, 0.85, 0.95)
_GROWN_COLOUR = (1.00, 0.55, 0.10)
_ORIGIN_REFUSED = 1008  # websocket close code: policy violation


def render_size(canvas_width, canvas_height, *, rows) -> tuple[int, int]:
    """The ``(width, height)`` [pixels] to render for a browser canvas of ``canvas_width`` x ``canvas_height``
    pixels at a resolution of ``rows``: never more rows than the canvas has, the width following its aspect, then
    scaled down, keeping the aspect, to at most :data:`MAX_RENDER_SIDE` a side and :data:`MAX_RENDER_PIXELS` in
    all. A value that is not a positive finite number (a browser's bad message) counts as 1.
    """

    def positive(value) -> float:
        try:
            value = float(value)
        except (TypeError, ValueError, OverflowError):
            return 1.0
        return min(value, 1e12) if math.isfinite(value) and value >= 1.0 else 1.0

    canvas_width, canvas_height = positive(canvas_width), positive(canvas_height)
    height = float(int(min(positive(rows), canvas_height)))
    width = max(1.0, round(height * canvas_width / canvas_height))
    shrink = min(1.0, MAX_RENDER_SIDE / width, MAX_RENDER_SIDE / height,
                 math.sqrt(MAX_RENDER_PIXELS / (width * height)))
    if shrink < 1.0:
        width, height = max(1.0, math.floor(width * shrink)), max(1.0, math.floor(height * shrink))
    return int(width), int(height)


def _host_and_port(netloc: str, default_port: int) -> tuple[str, int] | None:
    """``("name", port)`` of a ``name[:port]`` or ``[v6]:port`` network location; None when malformed."""
    try:
        parts = urllib.parse.urlsplit("//" + netloc)
        port = parts.port
    except ValueError:
        return None
    if not parts.hostname or parts.username is not None or parts.password is not None:
        return None
    return parts.hostname.lower(), default_port if port is None else port


def origin_refusal(origin: str | None, host: str | None, *, listen_host: str) -> str | None:
    """Why a websocket handshake with these ``Origin`` and ``Host`` headers is refused; None when it is accepted.

    Accepted are pages loaded from the viewer itself: the ``Origin`` (an ``http`` or ``https`` page) must name the
    host and port of the ``Host`` the browser connected to, and that host must be this machine by a name no web
    page can redirect (``localhost``, an IP address, or ``listen_host`` as given to ``--host``), which keeps out
    pages whose domain name was pointed at this machine (DNS rebinding). Browsers always send an ``Origin`` with a
    websocket; a client without one is refused too.

    Args:
        origin: the handshake's ``Origin`` header (None: absent).
        host: its ``Host`` header (None: absent).
        listen_host: the address the viewer listens on.
    """
    if not origin:
        return "no Origin header (only the viewer's own page may connect)"
    try:
        parts = urllib.parse.urlsplit(origin)
    except ValueError:
        parts = None
    default_port = {"http": 80, "https": 443}.get(parts.scheme.lower()) if parts is not None else None
    page = _host_and_port(parts.netloc, default_port) if default_port is not None else None
    if page is None or parts.path not in ("", "/"):
        return f"Origin {origin!r} is not a web page's origin"
    served = _host_and_port(host or "", default_port)
    if served is None:
        return f"no usable Host header (got {host!r})"
    if page != served:
        return f"Origin {origin!r} is another site than the viewer ({served[0]}:{served[1]})"
    name = served[0].strip("[]")
    try:
        ipaddress.ip_address(name)
    except ValueError:
        if name not in ("localhost", listen_host.lower()):
            return (f"Origin {origin!r} names this machine by {name!r}, which a web page could point elsewhere; "
                    "open the viewer at localhost, an IP address or the --host name")
    return None


def opencv_camera(camera_to_world_wxyz, position, vertical_fov: float, *, height: int, aspect: float) -> OrbitCamera:
    """A browser's camera as an OpenCV pinhole camera (docs/conventions.md) rendering ``height`` pixels.

    Args:
        camera_to_world_wxyz: [4] rotation (w, x, y, z) of the camera's axes in the world, OpenCV axes (x right,
            y down, z forward), as viser reports it.
        position: [3] the camera centre [world units].
        vertical_fov: the vertical field of view [radians], edge to edge of the image.
        height: image height [pixels]; the width is ``round(height * aspect)``.
        aspect: width / height of the browser's canvas.
    """
    if not (0.0 < vertical_fov < math.pi):
        raise ValueError(f"vertical field of view must lie in (0, pi) radians, got {vertical_fov}")
    rotation = quat_to_matrix(np.asarray(camera_to_world_wxyz, dtype=np.float64) /
                              np.linalg.norm(camera_to_world_wxyz))
    world_to_camera = np.eye(4)
    world_to_camera[:3, :3] = rotation.T
    world_to_camera[:3, 3] = -rotation.T @ np.asarray(position, dtype=np.float64)
    height = max(1, int(height))
    width = max(1, int(round(height * aspect)))
    focal = 0.5 * height / math.tan(0.5 * vertical_fov)
    K = np.array([[focal, 0.0, (width - 1) * 0.5], [0.0, focal, (height - 1) * 0.5], [0.0, 0.0, 1.0]])
    return OrbitCamera(K.astype(np.float32), world_to_camera.astype(np.float32), width, height)


def skeleton_segments(rig, transforms, *, joint_count: int) -> tuple[np.ndarray, np.ndarray]:
    """Line segments of a posed skeleton: each joint's bone (head to tail) and, where a joint does not start at
    its parent's tail (a grown joint), a link from the parent's head to it.

    Args:
        rig: the skeleton with any grown joints appended (:meth:`warpavatar.model.Avatar.rig`), J+E joints.
        transforms: [J+E,4,4] rest-to-posed transforms of those joints (``posed["bone_transforms"]``).
        joint_count: J, the skeleton's own joints (those after them are grown ones).

    Returns:
        ``(points [S,2,3] float32 [world units], grown [S] bool)``: the segments' ends, and whether each belongs
        to a grown joint.
    """
    transforms = np.asarray(transforms, dtype=np.float64)
    heads = np.asarray(rig.heads, dtype=np.float64)
    tails = np.asarray(rig.tails, dtype=np.float64)

    def posed(points):
        return np.einsum("jab,jb->ja", transforms[:, :3, :3], points) + transforms[:, :3, 3]

    posed_heads, posed_tails = posed(heads), posed(tails)
    grown = np.arange(len(heads)) >= joint_count
    segments, flags = [np.stack([posed_heads, posed_tails], axis=1)], [grown]
    for joint, parent in enumerate(rig.parents):
        if parent >= 0 and np.linalg.norm(heads[joint] - tails[parent]) > 1e-6:
            segments.append(np.stack([posed_heads[parent], posed_heads[joint]])[None])
            flags.append(grown[joint:joint + 1])
    return np.concatenate(segments).astype(np.float32), np.concatenate(flags)


class AvatarViewer:
    """Serve a web page that shows an avatar driven by a motion, rendered on this machine as the camera moves.

    Args:
        avatar: the :class:`~warpavatar.model.Avatar` (on its device: CPU or CUDA).
        motion: the :class:`~warpavatar.io.motion.Motion` to play (already retargeted to the avatar).
        part_inputs: explicit per-frame inputs of the avatar's parts by part name, frame first (the grown joints'
            rotations), as ``warpavatar-render`` takes them.
        host: address to listen on; port: TCP port (0: any free one; a busy one moves to the next free port).
        image_height: height of the rendered images [pixels] at start (the page can change it).
        background: [3] background colour of the renders, 0..1.
        fps: playback rate [frames per second] at start (default: the motion's).
        show_skeleton: draw the skeleton at start; play: start playing.
        progress: show a progress bar while parts roll the motion out.

    Attributes:
        url: the page's address. ``render_count``: images sent so far; ``last_image``: the last one [H,W,3] uint8;
        ``last_render_seconds``: how long posing and rasterizing it took; ``frame``: the frame shown;
        ``last_error``: the last render's failure (None: none failed).
    """

    def __init__(self, avatar, motion, *, part_inputs=None, host: str = "127.0.0.1", port: int = 8080,
                 image_height: int = 512, background=(0.0, 0.0, 0.0), fps: float | None = None,
                 show_skeleton: bool = False, play: bool = False, progress: bool = False):
        import viser

        if image_height < 1:
            raise ValueError(f"--image-size must be a positive number of pixels, got {image_height}")
        self.avatar = avatar
        self.motion = motion
        self.device = avatar.gaussians.means.device
        self.frame_count = int(motion.bone_transforms.shape[0])
        self.part_inputs = part_inputs or {}
        self.background = torch.as_tensor(background, dtype=torch.float32, device=self.device)
        with torch.no_grad():
            avatar.prepare_sequence(motion.bone_transforms, frame_ids=motion.frame_ids, fps=motion.fps,
                                    progress=progress)
            self.grid = avatar.field.grid_weights()
        self.rig = avatar.rig()
        self.render_count = 0
        self.last_image: np.ndarray | None = None
        self.last_render_seconds = 0.0
        self.last_error: str | None = None
        self.frame = -1
        self._posed = None
        self._sent: dict[int, tuple] = {}
        self._cameras_known: set[int] = set()
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._playing = play
        self._play_origin = (time.monotonic(), 0)

        self.refused_connections = 0
        self._refused_origins: set[str] = set()
        self._listen_host = host
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self._refuse_foreign_pages()
        self.server.scene.set_up_direction(tuple(float(v) for v in np.asarray(avatar.skeleton.up)))
        self._set_initial_camera()
        self._build_gui(fps or motion.fps, image_height, show_skeleton)
        self.server.on_client_connect(self._on_connect)
        self.server.on_client_disconnect(self._on_disconnect)
        self._thread = threading.Thread(target=self._render_loop, name="warpavatar-view render", daemon=True)
        self._thread.start()

    # -------------------------------------------------------------------------------------------- security
    def _refuse_foreign_pages(self) -> None:
        """Close every websocket whose handshake :func:`origin_refusal` refuses, before it receives or sends
        anything.

        viser (1.x) has no hook at the handshake, so this hooks its websocket server's connect callbacks: they run
        once the handshake is done, after viser registers the client and before the client's first message is
        read or anything is sent to it. Connections made while the viewer started are checked here too.
        """
        websocket_server = getattr(self.server, "_websock_server", None)
        connections = getattr(websocket_server, "_live_connections", None)
        if websocket_server is None or not isinstance(connections, dict):
            self.server.stop()
            import viser

            raise RuntimeError("warpavatar-view cannot check the origin of connections with this version of viser "
                               f"({viser.__version__}): pip install 'viser>=1.1,<2'")

        async def refuse_foreign_page(client) -> None:
            connection = connections.get(client.client_id)
            if connection is not None and self._refused(connection):
                await connection.close(_ORIGIN_REFUSED, "only the viewer's own page may connect")

        websocket_server.on_client_connect(refuse_foreign_page)
        loop = websocket_server._background_event_loop
        for connection in list(connections.values()):
            if self._refused(connection) and loop is not None:
                asyncio.run_coroutine_threadsafe(connection.close(_ORIGIN_REFUSED, "only the viewer's own page may "
                                                                                   "connect"), loop)

    def _refused(self, connection) -> bool:
        """Whether a websocket connection must be closed (:func:`origin_refusal`); says so once per origin."""
        request = getattr(connection, "request", None)
        headers = getattr(request, "headers", None)
        origin = headers.get("Origin") if headers is not None else None
        reason = origin_refusal(origin, headers.get("Host") if headers is not None else None,
                                listen_host=self._listen_host)
        if reason is None:
            return False
        self.refused_connections += 1
        if str(origin) not in self._refused_origins:
            self._refused_origins.add(str(origin))
            print(f"warpavatar-view: refused a connection: {reason}", file=sys.stderr)
        return True

    # ------------------------------------------------------------------------------------------------ page
    @property
    def url(self) -> str:
        host = self.server.get_host()
        shown = "localhost" if host in ("0.0.0.0", "::", "") else host
        return f"http://{shown}:{self.server.get_port()}/"

    def _set_initial_camera(self) -> None:
        """Start looking at the rest pose's centre from where the training camera stood (the avatar's shading
        origin), else from ``warpavatar-render --orbit``'s first camera, close enough that the body fills most
        of a 40-degree field of view."""
        skeleton = self.avatar.skeleton
        camera = orbit_cameras(skeleton, 1, field_of_view_degrees=40.0)[0]
        rotation, translation = camera.world_to_camera[:3, :3], camera.world_to_camera[:3, 3]
        points = np.concatenate([skeleton.heads, skeleton.tails]).astype(np.float64)
        centre = 0.5 * (points.min(0) + points.max(0))
        offset = -rotation.T @ translation - centre
        origin = self.avatar.shading_origin
        if origin is not None:
            towards = origin.detach().cpu().numpy().astype(np.float64) - centre
            if np.linalg.norm(towards) > 1e-6:
                offset = towards / np.linalg.norm(towards) * np.linalg.norm(offset)
        initial = self.server.initial_camera
        initial.position = tuple(float(v) for v in centre + 0.65 * offset)
        initial.look_at = tuple(float(v) for v in centre)
        initial.up = tuple(float(v) for v in np.asarray(skeleton.up))
        initial.fov = math.radians(40.0)

    def _build_gui(self, fps: float, image_height: int, show_skeleton: bool) -> None:
        gui = self.server.gui
        with gui.add_folder("Motion"):
            last = max(1, self.frame_count - 1)
            self.frame_slider = gui.add_slider("frame", min=0, max=last, step=1, initial_value=0,
                                               disabled=self.frame_count < 2,
                                               hint=f"index into the motion's {self.frame_count} frames")
            self.play_button = gui.add_button("Pause" if self._playing else "Play", disabled=self.frame_count < 2)
            self.fps_input = gui.add_number("fps", float(fps), min=0.1, max=240.0, step=0.1,
                                            hint="playback rate [frames per second]")
            self.frame_text = gui.add_markdown("")
        with gui.add_folder("Display"):
            self.skeleton_box = gui.add_checkbox("skeleton", show_skeleton,
                                                 hint="line segments between the posed joints; grown joints orange")
            self.resolution_slider = gui.add_slider("resolution", min=64, max=2160, step=16,
                                                    initial_value=int(min(2160, max(64, image_height))),
                                                    hint="height of the rendered image [pixels]")
            self.stats_text = gui.add_markdown(RENDERING_TEXT)

        @self.frame_slider.on_update
        def _(event) -> None:
            if event.client is not None:  # moved by a user: playback continues from there
                self._play_origin = (time.monotonic(), int(self.frame_slider.value))
            self._wake.set()

        @self.play_button.on_click
        def _(_) -> None:
            self._playing = not self._playing
            self._play_origin = (time.monotonic(), int(self.frame_slider.value))
            self.play_button.label = "Pause" if self._playing else "Play"
            self._wake.set()

        @self.fps_input.on_update
        def _(_) -> None:
            self._play_origin = (time.monotonic(), int(self.frame_slider.value))
            self._wake.set()

        @self.skeleton_box.on_update
        def _(_) -> None:
            if self._skeleton_lines is not None:
                self._skeleton_lines.visible = bool(self.skeleton_box.value)

        @self.resolution_slider.on_update
        def _(_) -> None:
            self._wake.set()

        self._skeleton_lines = None

    def _on_connect(self, client) -> None:
        # until its first render arrives the page shows the background colour and says it is rendering, rather
        # than a blank white page; set before any render of it can be sent, so it never covers one
        colour = (self.background.clamp(0, 1) * 255).round().to(torch.uint8).cpu().numpy()
        client.scene.set_background_image(np.broadcast_to(colour, (8, 8, 3)).copy(), format="png")
        self.stats_text.content = RENDERING_TEXT

        def camera_known() -> None:
            self._cameras_known.add(client.client_id)
            self._wake.set()

        client.camera.on_update(lambda _: camera_known())
        try:  # the page may have sent its camera while this ran (viser asserts while none has come)
            client.camera.update_timestamp
        except AssertionError:
            return
        camera_known()

    def _on_disconnect(self, client) -> None:
        self._cameras_known.discard(client.client_id)
        self._sent.pop(client.client_id, None)

    # ----------------------------------------------------------------------------------------------- loop
    def set_frame(self, frame: int) -> None:
        """Show motion frame ``frame`` (as moving the timeline does)."""
        if not 0 <= frame < self.frame_count:
            raise ValueError(f"frame {frame} outside the motion's {self.frame_count} frames")
        self._play_origin = (time.monotonic(), frame)
        self.frame_slider.value = frame
        self._wake.set()

    def _advance_playback(self) -> float:
        """Move the timeline on while playing; returns how long to wait before the next frame is due [s]."""
        if not self._playing or self.frame_count < 2:
            return 0.25
        fps = max(0.1, float(self.fps_input.value))
        start, first = self._play_origin
        elapsed = (time.monotonic() - start) * fps
        frame = (first + int(elapsed)) % self.frame_count
        if frame != int(self.frame_slider.value):
            self.frame_slider.value = frame
        return max(0.0, (1.0 - (elapsed - int(elapsed))) / fps)

    def _render_loop(self) -> None:
        while not self._stop.is_set():
            timeout = self._advance_playback()
            try:
                self._render_pending()
            except Exception as error:  # noqa: BLE001 - one bad render must not end the page; say it there
                self.last_error = f"render failed: {type(error).__name__}: {error}"
                self.stats_text.content = self.last_error
                print(f"warpavatar-view: {self.last_error}", file=sys.stderr)
            self._wake.wait(timeout)
            self._wake.clear()

    @torch.no_grad()
    def _pose(self, frame: int) -> None:
        bones = torch.as_tensor(self.motion.bone_transforms[frame], dtype=torch.float32, device=self.device)
        inputs = {name: torch.as_tensor(values[frame], device=self.device)
                  for name, values in self.part_inputs.items()}
        self._posed = self.avatar.pose(bones, frame_index=frame, grid=self.grid, inputs=inputs)
        self.frame = frame
        points, grown = skeleton_segments(self.rig, self._posed["bone_transforms"].cpu().numpy(),
                                          joint_count=self.avatar.joint_count)
        colours = np.where(grown[:, None, None], _GROWN_COLOUR, _SKELETON_COLOUR) * np.ones((1, 2, 3))
        self._skeleton_lines = self.server.scene.add_line_segments(
            "/skeleton", points, colours.astype(np.float32), thickness=2.0, thickness_units="screen",
            visible=bool(self.skeleton_box.value))
        frame_id = int(self.motion.frame_ids[frame])
        self.frame_text.content = f"frame {frame + 1} of {self.frame_count} (frame id {frame_id})"

    @torch.no_grad()
    def _render_pending(self) -> None:
        """Render for every browser whose camera, frame, resolution or background changed since its last image."""
        frame = int(self.frame_slider.value)
        height = int(self.resolution_slider.value)
        for client_id, client in list(self.server.get_clients().items()):
            if client_id not in self._cameras_known:
                continue
            camera = client.camera
            state = (camera.update_timestamp, frame, height)
            if self._sent.get(client_id) == state:
                continue
            start = time.perf_counter()
            if frame != self.frame or self._posed is None:
                self._pose(frame)
            # never more pixels than the browser shows, nor than the caps allow
            width, rows = render_size(camera.image_width, camera.image_height, rows=height)
            view = opencv_camera(camera.wxyz, camera.position, camera.fov, height=rows, aspect=width / rows)
            image, _, _ = self.avatar.rasterize(self._posed, view, background=self.background)
            pixels = (image.clamp(0, 1) * 255).round().to(torch.uint8).cpu().numpy()
            client.scene.set_background_image(pixels, format="jpeg", jpeg_quality=90)
            self._sent[client_id] = state
            with self._lock:
                self.last_image = pixels
                self.last_render_seconds = time.perf_counter() - start
                self.render_count += 1
            self.stats_text.content = (f"{view.width}x{view.height} pixels, "
                                       f"{1000 * self.last_render_seconds:.0f} ms on {self.device}")

    # ------------------------------------------------------------------------------------------- lifetime
    def serve_forever(self) -> None:
        """Block until interrupted (Ctrl+C), then stop."""
        try:
            while not self._stop.is_set():
                time.sleep(0.5)
        finally:
            self.stop()

    def stop(self) -> None:
        """Stop rendering and close the server."""
        self._stop.set()
        self._wake.set()
        self._thread.join(timeout=10)
        self.server.stop()
