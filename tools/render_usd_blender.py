"""Import a Points USD written by ``warpavatar-animate --layout points`` into Blender and render one frame to PNG.

    pip install "bpy==4.5.*"     # Blender as a Python module (CPython 3.11 only, about 800 MB installed)
    python tools/render_usd_blender.py dance_points.usdc -o frame.png --frame 12

Blender (``bpy`` from PyPI) is optional and not a dependency of warpavatar: install it in a virtual environment of
its own, since it pins numpy 1.x. The script goes through Blender's own USD importer, exactly as File > Import >
Universal Scene Description does, so the picture shows what a Blender user gets: the ``UsdGeom.Points`` prim
becomes a point cloud whose points are spheres of radius ``widths / 2`` (the Gaussians' largest standard
deviation), coloured by the ``displayColor`` primvar (each Gaussian's SH degree-0 colour) and faded by
``displayOpacity``; a ``--skeleton`` export adds the armature. The camera looks at the avatar from the front
(``--azimuth`` turns it), Cycles renders on the CPU.

Blender's importer sets the scene's frame range from the stage's ``startTimeCode`` / ``endTimeCode`` and shows time
code t at frame t, but it does not read the stage's frame rate (Blender 4.5 and 5.0): the scene stays at 24 fps
unless set. This script sets it from the stage's ``framesPerSecond`` (read with the OpenUSD Python module that
Blender bundles) and prints it; in Blender's interface, set Output Properties > Format > Frame Rate to it.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

from blender_scene import add_camera_and_lights, render_still, set_scene_frame_rate


def _blender_pxr():
    """OpenUSD's Python module as bundled with Blender (the ``bpy`` wheel keeps it off ``sys.path``)."""
    import bpy

    try:
        from pxr import Usd
    except ImportError:
        lib = os.path.join(bpy.utils.resource_path("LOCAL"), "python", "lib")
        version = f"python{sys.version_info.major}.{sys.version_info.minor}"
        for folder in (os.path.join(lib, version, "site-packages"), os.path.join(lib, "site-packages")):
            if os.path.isdir(os.path.join(folder, "pxr")) and folder not in sys.path:
                sys.path.append(folder)
        from pxr import Usd
    return Usd


def stage_frame_rate(path: str) -> float:
    """The stage's ``framesPerSecond`` (the rate to play it at)."""
    stage = _blender_pxr().Stage.Open(path)
    if stage is None:
        raise SystemExit(f"error: {path}: OpenUSD cannot open it")
    return float(stage.GetFramesPerSecond())


def display_colour_material(bpy):
    """Principled BSDF with base colour and alpha from the point attributes ``displayColor`` and ``displayOpacity``."""
    material = bpy.data.materials.new("GaussianDisplayColor")
    material.use_nodes = True
    nodes, links = material.node_tree.nodes, material.node_tree.links
    shader = nodes["Principled BSDF"]
    colour = nodes.new("ShaderNodeAttribute")
    colour.attribute_type, colour.attribute_name = "GEOMETRY", "displayColor"
    opacity = nodes.new("ShaderNodeAttribute")
    opacity.attribute_type, opacity.attribute_name = "GEOMETRY", "displayOpacity"
    links.new(colour.outputs["Color"], shader.inputs["Base Color"])
    # half of the colour as emission, so the spheres keep the avatar's colours (a splat renderer shows them unlit)
    links.new(colour.outputs["Color"], shader.inputs["Emission Color"])
    shader.inputs["Emission Strength"].default_value = 0.5
    links.new(opacity.outputs["Fac"], shader.inputs["Alpha"])
    shader.inputs["Roughness"].default_value = 0.6
    return material


def point_bounds(bpy, objects) -> tuple[list[float], list[float]]:
    """World-space box (low, high corners) of 99 % of the evaluated points at the current frame (strays left out)."""
    import numpy as np

    depsgraph = bpy.context.evaluated_depsgraph_get()
    positions = []
    for obj in objects:
        evaluated = obj.evaluated_get(depsgraph)
        local = np.empty(3 * len(evaluated.data.points), dtype=np.float64)
        evaluated.data.attributes["position"].data.foreach_get("vector", local)
        matrix = np.array(evaluated.matrix_world)
        positions.append(local.reshape(-1, 3) @ matrix[:3, :3].T + matrix[:3, 3])
    positions = np.concatenate(positions)
    return np.percentile(positions, 0.5, axis=0).tolist(), np.percentile(positions, 99.5, axis=0).tolist()


def frame_points(bpy, low, high, *, azimuth_deg: float, size: int) -> None:
    """A 35 mm camera framing the box from the front (-Y, Blender's front view, turned by ``azimuth_deg``), a sun."""
    extent = max(b - a for a, b in zip(low, high))
    add_camera_and_lights(bpy, [(a + b) / 2 for a, b in zip(low, high)], extent=extent, depth=extent / 2,
                          width=size, height=size, azimuth_deg=azimuth_deg, lens_mm=35.0, fill=0.55, elevation=0.15,
                          sun_elevation_deg=40.0, sun_azimuth_offset_deg=-30.0, background=(0.05, 0.06, 0.08),
                          background_strength=1.0)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("usd", help="the .usdc written by warpavatar-animate --layout points (with or without "
                                    "--skeleton)")
    parser.add_argument("-o", "--output", required=True, help="the PNG file to write")
    parser.add_argument("--frame", type=int, default=None,
                        help="scene frame (= USD time code) to render (default: the stage's startTimeCode)")
    parser.add_argument("--size", type=int, default=320, help="image width and height [px] (default: %(default)s)")
    parser.add_argument("--samples", type=int, default=16, help="Cycles samples per pixel (default: %(default)s)")
    parser.add_argument("--azimuth", type=float, default=0.0,
                        help="camera azimuth [degrees] about the up axis, 0 = Blender's front view (-Y) "
                             "(default: %(default)s)")
    args = parser.parse_args(argv)
    if not os.path.isfile(args.usd):
        parser.error(f"{args.usd}: no such file")
    try:
        import bpy
    except ImportError:
        parser.error('this tool needs Blender as a Python module: pip install "bpy==4.5.*" (CPython 3.11)')

    start = time.time()
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    if bpy.ops.wm.usd_import(filepath=os.path.abspath(args.usd)) != {"FINISHED"}:
        raise SystemExit(f"error: {args.usd}: Blender's USD import failed")
    clouds = [obj for obj in scene.objects if obj.type == "POINTCLOUD"]
    if not clouds:
        raise SystemExit(f"error: {args.usd}: no point cloud imported (write it with --layout points)")
    fps = stage_frame_rate(args.usd)
    set_scene_frame_rate(scene, fps)
    frame = scene.frame_start if args.frame is None else args.frame
    scene.frame_set(frame)
    material = display_colour_material(bpy)
    for cloud in clouds:
        cloud.data.materials.append(material)
    low, high = point_bounds(bpy, clouds)
    frame_points(bpy, low, high, azimuth_deg=args.azimuth, size=args.size)
    render_still(bpy, scene, args.output, samples=args.samples)
    count = sum(len(cloud.data.points) for cloud in clouds)
    armatures = [obj.name for obj in scene.objects if obj.type == "ARMATURE"]
    print(f"{args.usd}: {count} points in {len(clouds)} point cloud(s), armature(s) {armatures or 'none'}; "
          f"frames {scene.frame_start}..{scene.frame_end} at {scene.render.fps / scene.render.fps_base:g} fps "
          f"(the stage's framesPerSecond); frame {frame} -> {args.output} in {time.time() - start:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
