"""Scene set-up shared by the Blender render tools (``render_mesh_blender.py``, ``render_usd_blender.py``): the
scene's frame rate, a camera with a sun and a world light framing what was imported, and a Cycles still on the CPU.

Runs inside Blender's Python (``bpy`` from PyPI, CPython 3.11); each function takes ``bpy`` or a scene from its
caller, so importing this module needs no Blender.
"""

from __future__ import annotations

import math
import os

__all__ = ["set_scene_frame_rate", "add_camera_and_lights", "render_still"]


def set_scene_frame_rate(scene, fps: float) -> None:
    """Blender keeps the rate as an integer over a base: 29.97 becomes 30 / 1.001."""
    scene.render.fps = max(1, round(fps))
    scene.render.fps_base = scene.render.fps / fps


def add_camera_and_lights(bpy, centre, *, extent: float, depth: float, width: int, height: int,
                          azimuth_deg: float, lens_mm: float, sensor_fit: str = "AUTO", fill: float,
                          elevation: float, sun_elevation_deg: float, sun_azimuth_offset_deg: float,
                          background: tuple[float, float, float], background_strength: float) -> None:
    """Add a camera that looks at ``centre`` from the front, a sun and a uniform world light; set the resolution.

    Args:
        bpy: Blender's module.
        centre: (3,) world point [m] the camera aims at.
        extent: the size [m] the view must hold across the field of view that ``sensor_fit`` picks.
        depth: distance [m] added in front of that (half the box's depth towards the camera).
        width, height: image size [px].
        azimuth_deg: camera turn [degrees] about +Z; 0 looks from -Y (Blender's front view).
        lens_mm: focal length [mm] (the sensor stays Blender's default).
        sensor_fit: Blender's sensor fit, ``"AUTO"`` (the field of view of the sensor's width, ``angle``) or
            ``"VERTICAL"`` (the field of view of its height, ``angle_y``).
        fill: the camera distance is ``fill * extent / tan(half field of view) + depth``; 0.5 puts the extent
            edge to edge.
        elevation: the camera direction's Z before normalising (its X, Y have unit length): how far above it looks.
        sun_elevation_deg: the sun's rotation about X [degrees] (0 shines straight down).
        sun_azimuth_offset_deg: the sun's turn about Z [degrees] relative to ``azimuth_deg``.
        background: the world's linear RGB colour.
        background_strength: the world light's strength.
    """
    import mathutils

    centre = mathutils.Vector(centre)
    camera_data = bpy.data.cameras.new("Camera")
    camera_data.lens = lens_mm
    camera_data.sensor_fit = sensor_fit
    half_fov = 0.5 * (camera_data.angle_y if sensor_fit == "VERTICAL" else camera_data.angle)
    distance = fill * extent / math.tan(half_fov) + depth
    angle = math.radians(azimuth_deg)
    direction = mathutils.Vector((math.sin(angle), -math.cos(angle), elevation)).normalized()
    camera = bpy.data.objects.new("Camera", camera_data)
    camera.location = centre + distance * direction
    camera.rotation_euler = (centre - camera.location).to_track_quat("-Z", "Y").to_euler()
    scene = bpy.context.scene
    scene.collection.objects.link(camera)
    scene.camera = camera
    sun = bpy.data.objects.new("Sun", bpy.data.lights.new("Sun", "SUN"))
    sun.data.energy = 3.0
    sun.rotation_euler = (math.radians(sun_elevation_deg), 0.0, math.radians(azimuth_deg + sun_azimuth_offset_deg))
    scene.collection.objects.link(sun)
    world = bpy.data.worlds.new("World")
    world.use_nodes = True
    light = world.node_tree.nodes["Background"]
    light.inputs["Color"].default_value = (*background, 1.0)
    light.inputs["Strength"].default_value = background_strength
    scene.world = world
    scene.render.resolution_x, scene.render.resolution_y = width, height
    scene.render.resolution_percentage = 100


def render_still(bpy, scene, output: str, *, samples: int) -> None:
    """Render the scene's current frame with Cycles on the CPU (denoised), to the PNG file ``output``.

    Cycles, since Eevee and Workbench need a GPU context that the ``bpy`` module does not have headless.
    """
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = samples
    scene.cycles.use_denoising = True
    scene.render.image_settings.file_format = "PNG"
    scene.render.filepath = os.path.abspath(output)
    bpy.ops.render.render(write_still=True)
