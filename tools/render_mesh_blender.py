"""Import a mesh export of ``warpavatar-export`` (``.glb`` / ``.gltf`` / ``.usd`` / ``.usdc`` / ``.usda`` /
``.usdz``) into Blender and render one frame of its motion to PNG.

    python3.11 -m venv ~/.cache/warpavatar-bpy && ~/.cache/warpavatar-bpy/bin/pip install bpy==4.5.3
    ~/.cache/warpavatar-bpy/bin/python tools/render_mesh_blender.py avatar.usdc -o frame.png --frame 12

Blender (``bpy`` from PyPI, CPython 3.11) is optional and not a dependency of warpavatar: it pins numpy 1.x, so
it lives in a virtual environment of its own. The file goes through Blender's own importer with its default
options, exactly as File > Import does, so the picture shows what a Blender user gets: the armature, the mesh
skinned by it (and, in a USD file with vertex offsets, its time-sampled points as a Mesh Sequence Cache), the
material with the texture atlas. The camera frames the posed mesh from the front (Blender's front view, from
-Y; ``--azimuth`` turns it about the up axis), a sun and a grey sky light it, Cycles renders on the CPU (Eevee and
Workbench need a GPU context the ``bpy`` module does not have headless).

Frames: ``--frame`` is the motion's time code (its frame id less the first). Blender's USD importer shows time
code c at scene frame c; its glTF importer puts animation time t at frame ``t * scene fps``, so the scene's rate
is set first to the fps that ``warpavatar-export`` records in the glTF animation's ``extras`` (30 without it),
which makes frame c time code c there too.
"""

from __future__ import annotations

import argparse
import json
import os
import struct
import sys
import time

from blender_scene import add_camera_and_lights, render_still, set_scene_frame_rate

USD_SUFFIXES = (".usd", ".usdc", ".usda", ".usdz")
GLTF_SUFFIXES = (".glb", ".gltf")


def gltf_fps(path: str, default: float = 30.0) -> float:
    """The motion's fps that ``warpavatar-export`` writes in a glTF file's first animation (``extras.fps``)."""
    with open(path, "rb") as stream:
        head = stream.read(20)
        if head[:4] == b"glTF":
            length = struct.unpack_from("<I", head, 12)[0]
            document = json.loads(stream.read(length))
        else:
            document = json.loads(head + stream.read())
    animations = document.get("animations") or [{}]
    fps = (animations[0].get("extras") or {}).get("fps")
    return float(fps) if isinstance(fps, (int, float)) and fps > 0 else default


def skinned_meshes(scene) -> list:
    """The imported mesh objects (those with an Armature modifier first; all meshes if none has one)."""
    meshes = [obj for obj in scene.objects if obj.type == "MESH"]
    skinned = [obj for obj in meshes if any(modifier.type == "ARMATURE" for modifier in obj.modifiers)]
    return skinned or meshes


def mesh_bounds(bpy, objects) -> tuple[list[float], list[float]]:
    """World-space box (low, high corners) of the evaluated vertices at the current frame."""
    import numpy as np

    depsgraph = bpy.context.evaluated_depsgraph_get()
    positions = []
    for obj in objects:
        evaluated = obj.evaluated_get(depsgraph)
        mesh = evaluated.to_mesh()
        local = np.empty(3 * len(mesh.vertices), dtype=np.float64)
        mesh.vertices.foreach_get("co", local)
        evaluated.to_mesh_clear()
        matrix = np.array(evaluated.matrix_world)
        positions.append(local.reshape(-1, 3) @ matrix[:3, :3].T + matrix[:3, 3])
    positions = np.concatenate(positions)
    return positions.min(axis=0).tolist(), positions.max(axis=0).tolist()


def frame_mesh(bpy, low, high, *, azimuth_deg: float, width: int, height: int) -> None:
    """A 50 mm camera framing the box from the front (-Y, turned by ``azimuth_deg``), a sun and a grey sky light."""
    size = [b - a for a, b in zip(low, high)]
    across = max(size[0], size[1])
    add_camera_and_lights(bpy, [(a + b) / 2 for a, b in zip(low, high)],
                          extent=max(size[2], across * height / width),  # the taller of the box's height and width
                          depth=across / 2, width=width, height=height, azimuth_deg=azimuth_deg, lens_mm=50.0,
                          sensor_fit="VERTICAL", fill=0.6, elevation=0.12, sun_elevation_deg=50.0,
                          sun_azimuth_offset_deg=-35.0, background=(0.35, 0.38, 0.42), background_strength=0.8)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("mesh", help="the file written by warpavatar-export (.glb, .gltf, .usd, .usdc, .usda, .usdz)")
    parser.add_argument("-o", "--output", required=True, help="the PNG file to write")
    parser.add_argument("--frame", type=int, default=0,
                        help="the motion's time code to render (frame id less the first; default: %(default)s)")
    parser.add_argument("--width", type=int, default=480, help="image width [px] (default: %(default)s)")
    parser.add_argument("--height", type=int, default=540, help="image height [px] (default: %(default)s)")
    parser.add_argument("--samples", type=int, default=16, help="Cycles samples per pixel (default: %(default)s)")
    parser.add_argument("--azimuth", type=float, default=0.0,
                        help="camera azimuth [degrees] about the up axis, 0 = Blender's front view (-Y) "
                             "(default: %(default)s)")
    args = parser.parse_args(argv)
    suffix = os.path.splitext(args.mesh)[1].lower()
    if not os.path.isfile(args.mesh):
        parser.error(f"{args.mesh}: no such file")
    if suffix not in USD_SUFFIXES + GLTF_SUFFIXES:
        parser.error(f"{args.mesh}: give a .glb, .gltf, .usd, .usdc, .usda or .usdz file")
    try:
        import bpy
    except ImportError:
        parser.error("this tool needs Blender as a Python module: pip install bpy==4.5.3 (CPython 3.11), best in "
                     "a virtual environment of its own")

    start = time.time()
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    path = os.path.abspath(args.mesh)
    if suffix in GLTF_SUFFIXES:
        set_scene_frame_rate(scene, gltf_fps(path))
        result = bpy.ops.import_scene.gltf(filepath=path)
    else:
        result = bpy.ops.wm.usd_import(filepath=path)
    if result != {"FINISHED"}:
        raise SystemExit(f"error: {args.mesh}: Blender's import failed")
    meshes = skinned_meshes(scene)
    if not meshes:
        raise SystemExit(f"error: {args.mesh}: no mesh imported")
    scene.frame_set(args.frame)
    low, high = mesh_bounds(bpy, meshes)
    frame_mesh(bpy, low, high, azimuth_deg=args.azimuth, width=args.width, height=args.height)
    render_still(bpy, scene, args.output, samples=args.samples)
    armatures = [obj for obj in scene.objects if obj.type == "ARMATURE"]
    bones = sum(len(obj.data.bones) for obj in armatures)
    vertices = sum(len(obj.data.vertices) for obj in meshes)
    print(f"{args.mesh}: {vertices} vertices in {len(meshes)} mesh(es), {bones} bones; scene frames "
          f"{scene.frame_start}..{scene.frame_end} at {scene.render.fps / scene.render.fps_base:g} fps; frame "
          f"{args.frame} -> {args.output} in {time.time() - start:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
