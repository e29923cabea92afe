"""Import mesh exports into Blender (``bpy``, Blender as a Python module) and record what a Blender user gets.

    python tests/blender_check.py avatar.glb avatar.usdc --frames 0 3 6 --fps 30 -o result.npz

Run by ``tests/test_blender_import.py`` in a process of its own: Blender bundles its own OpenUSD, which must not
share a process with usd-core's ``pxr``, and the ``bpy`` wheel pins numpy 1.x, so it usually lives in a virtual
environment apart from the project's. For each file, in a fresh empty scene whose frame rate is ``--fps``: the
file goes through Blender's own importer (``import_scene.gltf`` for ``.glb`` / ``.gltf``, ``wm.usd_import`` for
``.usd*``, as File > Import does, default options); the skinned mesh (the mesh object with an Armature modifier) is
evaluated through the depsgraph at each of ``--frames`` and its vertices taken to world space. Written to ``-o``
(an ``.npz``): per file ``i``, ``positions_i`` [K,V,3] float64 [m]; where the mesh has shape keys (glTF morph
targets), ``widened_i``, the same with every shape key's slider range widened (Blender clamps a shape key's weight
to its slider range, [0, 1] unless the importer widened it); and ``info_i``, a JSON text with the file, the bone
names of its armature, the scene's frame range and fps after the import, the mesh's modifiers, vertex count, UV
layers, materials and shape keys' slider ranges, and the import time [s].
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np


def _skinned_mesh(scene):
    meshes = [obj for obj in scene.objects if obj.type == "MESH"]
    skinned = [obj for obj in meshes if any(modifier.type == "ARMATURE" for modifier in obj.modifiers)]
    if len(skinned) != 1:
        raise SystemExit(f"error: expected one skinned mesh, found {[obj.name for obj in skinned]} among "
                         f"{[obj.name for obj in meshes]}")
    return skinned[0]


def _world_vertices(bpy, obj) -> np.ndarray:
    depsgraph = bpy.context.evaluated_depsgraph_get()
    evaluated = obj.evaluated_get(depsgraph)
    mesh = evaluated.to_mesh()
    try:
        local = np.empty(3 * len(mesh.vertices), dtype=np.float64)
        mesh.vertices.foreach_get("co", local)
    finally:
        evaluated.to_mesh_clear()
    matrix = np.array(evaluated.matrix_world, dtype=np.float64)
    return local.reshape(-1, 3) @ matrix[:3, :3].T + matrix[:3, 3]


def check_file(bpy, path: str, frames: list[int], fps: float) -> tuple[np.ndarray, np.ndarray | None, dict]:
    """Import ``path`` into an empty scene at ``fps`` and evaluate its skinned mesh at ``frames``: as imported, and
    (where it has shape keys) again with their slider ranges widened to [-10, 10]."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.render.fps = max(1, round(fps))
    scene.render.fps_base = scene.render.fps / fps
    start = time.perf_counter()
    extension = os.path.splitext(path)[1].lower()
    if extension in (".glb", ".gltf"):
        result = bpy.ops.import_scene.gltf(filepath=os.path.abspath(path))
    else:
        result = bpy.ops.wm.usd_import(filepath=os.path.abspath(path))
    seconds = time.perf_counter() - start
    if result != {"FINISHED"}:
        raise SystemExit(f"error: {path}: Blender's import returned {result}")
    obj = _skinned_mesh(scene)
    armature = next(modifier.object for modifier in obj.modifiers if modifier.type == "ARMATURE")
    positions = []
    for frame in frames:
        scene.frame_set(frame)
        positions.append(_world_vertices(bpy, obj))
    keys = obj.data.shape_keys.key_blocks if obj.data.shape_keys else []
    slider_ranges = {key.name: [key.slider_min, key.slider_max] for key in keys}
    widened = None
    if keys:  # again with every shape key free to take any weight (Blender clamps weights to the slider range)
        for key in keys:
            key.slider_min, key.slider_max = -10.0, 10.0
        widened = []
        for frame in frames:
            scene.frame_set(frame)
            widened.append(_world_vertices(bpy, obj))
    info = {
        "file": path, "import_seconds": seconds, "bones": [bone.name for bone in armature.data.bones],
        "frame_start": scene.frame_start, "frame_end": scene.frame_end,
        "fps": scene.render.fps / scene.render.fps_base, "modifiers": [modifier.type for modifier in obj.modifiers],
        "vertex_count": len(obj.data.vertices), "mesh": obj.name, "armature": armature.name,
        "shape_key_ranges": slider_ranges,
        "uv_layers": [layer.name for layer in obj.data.uv_layers],
        "materials": [material.name for material in obj.data.materials if material is not None],
    }
    return np.stack(positions), (None if widened is None else np.stack(widened)), info


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("files", nargs="+", help=".glb / .gltf / .usd / .usdc / .usda / .usdz files")
    parser.add_argument("--frames", type=int, nargs="+", required=True, help="scene frames to evaluate")
    parser.add_argument("--fps", type=float, required=True, help="the scene's frame rate, set before each import")
    parser.add_argument("-o", "--output", required=True, help="the .npz to write")
    args = parser.parse_args(argv)
    start = time.perf_counter()
    import bpy

    started = time.perf_counter() - start
    arrays = {}
    for index, path in enumerate(args.files):
        positions, widened, info = check_file(bpy, path, args.frames, args.fps)
        info["bpy_import_seconds"] = started
        arrays[f"positions_{index}"] = positions
        if widened is not None:
            arrays[f"widened_{index}"] = widened
        arrays[f"info_{index}"] = np.array(json.dumps(info))
    np.savez(args.output, **arrays)
    return 0


if __name__ == "__main__":
    sys.exit(main())
