"""The .glb of warpavatar-export in three.js: headless Chromium (driven by Selenium through chromedriver, WebGL on
SwiftShader) loads it with three's GLTFLoader from a small local page, plays its animation with an AnimationMixer
and renders it with WebGLRenderer; the picture must show the avatar (not the background alone), and the bones must
move. three.js comes from its npm package (``npm install --prefix ~/.cache/warpavatar-node three``; the variable
WARPAVATAR_NODE_MODULES names another node_modules folder). The test skips where the browser or three.js is
missing, unless CI is set.

Run as a script, it makes docs/images/export_threejs.png from a fitted avatar:
``python3 tests/test_threejs_export.py AVATAR_DIR -o docs/images/export_threejs.png``.
"""

from __future__ import annotations

import base64
import contextlib
import functools
import http.server
import json
import os
import shutil
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))  # conftest, when run as a script

from conftest import CHROMEDRIVER, CHROMIUM, require_browser  # noqa: E402

BACKGROUND = (40, 44, 52)
"""The page's clear colour, RGB bytes."""

PAGE = """<!doctype html>
<html><head><meta charset="utf-8"><title>warpavatar glTF in three.js</title>
<style>html, body { margin: 0; background: #000; }</style>
<script type="importmap">
{"imports": {"three": "./three/build/three.module.js", "three/addons/": "./three/examples/jsm/"}}
</script></head>
<body>
<script type="module">
import * as THREE from "three";
import { GLTFLoader } from "three/addons/loaders/GLTFLoader.js";

const params = new URLSearchParams(location.search);
const width = Number(params.get("width")), height = Number(params.get("height"));
const steps = Number(params.get("steps")), at = Number(params.get("at"));
window.addEventListener("error", (event) => { window.__result = { error: String(event.message) }; });
try {
  const renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
  renderer.setPixelRatio(1);
  renderer.setSize(width, height);
  renderer.setClearColor(new THREE.Color().setRGB(BG_R / 255, BG_G / 255, BG_B / 255, THREE.SRGBColorSpace));
  document.body.appendChild(renderer.domElement);
  const scene = new THREE.Scene();
  scene.add(new THREE.HemisphereLight(0xffffff, 0x666666, 2.0));
  const sun = new THREE.DirectionalLight(0xffffff, 1.5);
  sun.position.set(1, 2, 3);
  scene.add(sun);
  const gltf = await new GLTFLoader().loadAsync("./avatar.glb");
  scene.add(gltf.scene);
  const skinned = [];
  gltf.scene.traverse((node) => { if (node.isSkinnedMesh) skinned.push(node); });
  const bones = skinned.length ? skinned[0].skeleton.bones : [];
  const bonePositions = () => bones.map((bone) => bone.getWorldPosition(new THREE.Vector3()));
  const mixer = new THREE.AnimationMixer(gltf.scene);
  const clip = gltf.animations[0];
  mixer.clipAction(clip).play();
  mixer.update(0);
  gltf.scene.updateMatrixWorld(true);
  const rest = bonePositions();
  // frame the avatar as it stands at the first frame, seen from the front (glTF's +Z)
  const box = new THREE.Box3().setFromObject(gltf.scene, true);
  const centre = box.getCenter(new THREE.Vector3()), size = box.getSize(new THREE.Vector3());
  const camera = new THREE.PerspectiveCamera(35, width / height, 0.01, 100);
  const distance = 0.62 * Math.max(size.y, size.x * height / width) / Math.tan(THREE.MathUtils.degToRad(35 / 2));
  camera.position.set(centre.x + 0.35 * distance, centre.y + 0.1 * size.y, centre.z + distance);
  camera.lookAt(centre);
  const dt = clip.duration * at / Math.max(steps, 1);
  for (let step = 0; step < steps; step++) {  // play the clip frame by frame, rendering each
    mixer.update(dt);
    renderer.render(scene, camera);
  }
  renderer.render(scene, camera);
  const moved = bonePositions().reduce((most, p, i) => Math.max(most, p.distanceTo(rest[i])), 0);
  window.__result = {
    image: renderer.domElement.toDataURL("image/png"), skinnedMeshes: skinned.length, bones: bones.length,
    duration: clip.duration, tracks: clip.tracks.length, time: mixer.time, moved: moved,
    triangles: skinned.length ? skinned[0].geometry.index.count / 3 : 0, size: size.toArray(),
    texture: Boolean(skinned.length && skinned[0].material.map && skinned[0].material.map.image),
  };
} catch (error) {
  window.__result = { error: String(error && error.stack || error) };
}
</script></body></html>
""".replace("BG_R", str(BACKGROUND[0])).replace("BG_G", str(BACKGROUND[1])).replace("BG_B", str(BACKGROUND[2]))


def node_modules() -> Path:
    """The node_modules folder that holds three.js: WARPAVATAR_NODE_MODULES, else
    ``~/.cache/warpavatar-node/node_modules``."""
    return Path(os.environ.get("WARPAVATAR_NODE_MODULES", "~/.cache/warpavatar-node/node_modules")).expanduser()


def require_three() -> Path:
    """three's package folder; skip where it is missing, except under CI, where it fails."""
    three = node_modules() / "three"
    if not (three / "build" / "three.module.js").is_file():
        message = (f"no three.js in {three.parent} (npm install --prefix ~/.cache/warpavatar-node three, or set "
                   "WARPAVATAR_NODE_MODULES)")
        if os.environ.get("CI"):
            pytest.fail(f"{message}; CI is set, so the three.js test must run")
        pytest.skip(message)
    return three


class _QuietHandler(http.server.SimpleHTTPRequestHandler):
    extensions_map = {**http.server.SimpleHTTPRequestHandler.extensions_map, ".js": "text/javascript",
                      ".glb": "model/gltf-binary"}

    def log_message(self, format, *args):  # noqa: A002 - the base class's name
        pass


@contextlib.contextmanager
def serve(folder: Path):
    """Serve ``folder`` over HTTP on a free local port, in a thread; yields the base address."""
    handler = functools.partial(_QuietHandler, directory=str(folder))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}"
    finally:
        server.shutdown()
        server.server_close()
        thread.join(timeout=10)


def _browser(user_data_dir: str, width: int, height: int):
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for flag in ("--headless=new", "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                 "--ignore-gpu-blocklist", "--disable-dev-shm-usage", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync",
                 f"--window-size={width + 40},{height + 40}", "--force-device-scale-factor=1",
                 f"--user-data-dir={user_data_dir}"):
        options.add_argument(flag)
    return webdriver.Chrome(options=options, service=Service(CHROMEDRIVER))


def render_in_threejs(glb: Path, three: Path, *, width: int = 320, height: int = 400, steps: int = 12,
                      at: float = 0.5, timeout: float = 120.0) -> tuple[np.ndarray, dict]:
    """Load ``glb`` in three.js in headless Chromium, play its first animation ``steps`` frames up to the share
    ``at`` of its duration, rendering each, and return the last picture ([H,W,3] uint8 RGB) and what the page
    reported (``skinnedMeshes``, ``bones``, ``duration`` [s], ``tracks``, ``time`` [s], ``moved``: the largest
    distance a bone moved from the first frame [m], ``triangles``, ``size`` [m], ``texture``)."""
    import cv2

    with tempfile.TemporaryDirectory(prefix="warpavatar-threejs-") as scratch:
        site = Path(scratch) / "site"
        site.mkdir()
        (site / "index.html").write_text(PAGE, encoding="utf-8")
        shutil.copy(glb, site / "avatar.glb")
        (site / "three").symlink_to(three, target_is_directory=True)
        with serve(site) as address:
            driver = _browser(str(Path(scratch) / "profile"), width, height)
            try:
                driver.get(f"{address}/index.html?width={width}&height={height}&steps={steps}&at={at}")
                end = time.monotonic() + timeout
                result = None
                while result is None:
                    result = driver.execute_script("return window.__result || null;")
                    if result is None:
                        assert time.monotonic() < end, "three.js did not finish loading and playing the .glb"
                        time.sleep(0.2)
                logs = []
                with contextlib.suppress(Exception):
                    logs = [entry["message"] for entry in driver.get_log("browser")]
            finally:
                driver.quit()
    assert "error" not in result, f"the page failed: {result['error']} (browser log: {logs})"
    encoded = result.pop("image").split(",", 1)[1]
    image = cv2.imdecode(np.frombuffer(base64.b64decode(encoded), np.uint8), cv2.IMREAD_COLOR)[..., ::-1]
    return np.ascontiguousarray(image), result


def foreground(image: np.ndarray) -> np.ndarray:
    """[H,W] bool: pixels that differ from :data:`BACKGROUND` by more than a few levels."""
    return np.abs(image.astype(np.int16) - np.array(BACKGROUND, np.int16)).max(axis=2) > 6


# ------------------------------------------------------------------------------------------------------- the test
@pytest.fixture(scope="module")
def exported_glb(avatar_dir, tmp_path_factory):
    """The small avatar exported as .glb at tiny settings, with 12 frames of the demo's dance."""
    from warpavatar import data
    from warpavatar.cli import export

    output = tmp_path_factory.mktemp("threejs") / "avatar.glb"
    motion = data.demo_subject_path() / "novel_pose" / "dance_cam000"
    code = export.main([str(avatar_dir), "-o", str(output), "--motion", str(motion), "--frames", "0:12",
                        "--triangles", "2000", "--texture-size", "256", "--view-count", "12", "--view-size", "96",
                        "--no-progress", "--device", "cpu"])
    assert code == 0
    return output


def test_threejs_loads_plays_and_draws_the_exported_glb(exported_glb):
    require_browser()
    three = require_three()
    image, report = render_in_threejs(exported_glb, three)
    assert report["skinnedMeshes"] == 1 and report["bones"] > 10 and report["texture"], report
    assert report["tracks"] == 2 * report["bones"] and report["duration"] > 0, report
    assert 400 <= report["triangles"] <= 2600, report
    assert report["time"] == pytest.approx(0.5 * report["duration"], rel=1e-3) and report["moved"] > 0.01, report
    mask = foreground(image)
    assert 0.02 < mask.mean() < 0.8, f"{mask.mean():.1%} of the picture differs from the background"
    rows, columns = np.nonzero(mask)
    assert rows.max() - rows.min() > 0.3 * image.shape[0], "the avatar is too small in the picture"
    colours = np.unique(image[mask] // 16, axis=0)
    assert len(colours) >= 8, f"the avatar has only {len(colours)} distinct colours: flat, or not textured"


# ------------------------------------------------------------------------------------------- the docs' picture
def main(argv=None) -> int:
    """Export a fitted avatar as .glb (its training motion) and save three.js's picture of it, mid-motion."""
    import argparse

    import cv2

    from warpavatar.cli import export

    parser = argparse.ArgumentParser(description=main.__doc__)
    parser.add_argument("avatar", type=Path, help="the fit's output folder")
    parser.add_argument("-o", "--output", type=Path, required=True, help="the PNG to write")
    parser.add_argument("--glb", type=Path, default=None, help="an exported .glb to show instead of exporting one")
    parser.add_argument("--width", type=int, default=480)
    parser.add_argument("--height", type=int, default=600)
    parser.add_argument("--at", type=float, default=0.5, help="share of the clip's duration to show")
    args = parser.parse_args(argv)
    three = node_modules() / "three"
    with tempfile.TemporaryDirectory() as scratch:
        glb = args.glb
        if glb is None:
            glb = Path(scratch) / "avatar.glb"
            if export.main([str(args.avatar), "-o", str(glb), "--device", "cpu"]) != 0:
                return 2
        image, report = render_in_threejs(glb, three, width=args.width, height=args.height, steps=24, at=args.at)
    print(json.dumps(report))
    if not cv2.imwrite(str(args.output), image[..., ::-1]):
        print(f"error: {args.output}: cannot be written", file=sys.stderr)
        return 2
    print(f"wrote {args.output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
