"""``warpavatar-export``: turn a fitted avatar into a textured, skinned triangle mesh and write it, with a motion,
in the format the output's suffix names (glTF 2.0, UsdSkel, or a static .obj / .ply)."""

from __future__ import annotations

import argparse
import contextlib
import re
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from warpavatar.cli.common import (TRAINING_MOTION_HELP, ArgumentParser, add_motion_arguments, check_output_path,
                                   default_device, friendly_errors, load_avatar, load_motion_for)
from warpavatar.fit.arguments import MAIN_GROUP, add_help_options, main_option
from warpavatar.io.output_files import output_lock
from warpavatar.mesh.build import (DEFAULT_TEXTURE_SIZE, DEFAULT_TRIANGLES, DEFAULT_VIEW_COUNT,
                                      DEFAULT_VIEW_SIZE)

__all__ = ["MESH_FORMATS", "MeshFormat", "mesh_format_for", "build_parser", "main"]

DESCRIPTION = """Make a triangle mesh of a fitted avatar and write it in the format the suffix of -o names.

The mesh is fused from renders of the avatar in its rest pose all around it (floaters dropped, decimated to
--triangles), unwrapped, textured from the same renders (a --texture-size atlas, and vertex colours), and skinned
with weights from the avatar's skinning field. The animated formats also hold the motion, as joint transforms per
frame, plus per-vertex offsets where the avatar moves beyond skinning (cloth, secondary motion). See
docs/export.md ("Meshes for engines").

Each file is written under a temporary name of its own beside -o and renamed once complete: an existing file at
-o (or a texture or material file beside it) is replaced only then, and a failure leaves it as it was. One
process at a time writes an output: a second one is refused while the first runs. Bad input is one line on
stderr, exit status 2.
"""

SUMMARY = """Make a textured, skinned triangle mesh of a fitted avatar and write it, with
its training motion or --motion, as glTF 2.0 (.glb/.gltf), UsdSkel (.usdc/.usd/
.usda/.usdz) or a static mesh (.obj/.ply). Bad input is one line on stderr, exit
status 2."""

EXAMPLES = (("warpavatar-export warpavatar-out/demo -o avatar.glb", "the demo avatar with its training motion, for "
             "three.js, Blender, Unity, Unreal"),
            ("warpavatar-export out/me -o dance.usdz --motion dance.bvh", "a BVH motion, as a UsdSkel package"),
            ("warpavatar-export out/me -o me.obj --triangles 20000", "the rest pose only, textured"))
"""The ``(command, comment)`` pairs ``warpavatar-export --help`` ends with."""


@dataclass(frozen=True)
class MeshFormat:
    """One output format of ``warpavatar-export``.

    Attributes:
        name: what messages call it.
        suffixes: the lower-case endings it writes, with the dot.
        animated: it holds the skin and a motion (False: the rest pose only).
        texture: it holds the UVs and texture atlas.
        vertex_colors: it holds the vertex colours.
    """

    name: str
    suffixes: tuple[str, ...]
    animated: bool
    texture: bool
    vertex_colors: bool


MESH_FORMATS = (
    # glTF multiplies COLOR_0 into the texture's colour, so its writer leaves vertex colours out of a textured mesh
    MeshFormat("glTF 2.0", (".glb", ".gltf"), animated=True, texture=True, vertex_colors=False),
    MeshFormat("UsdSkel", (".usd", ".usdc", ".usda", ".usdz"), animated=True, texture=True, vertex_colors=True),
    MeshFormat("OBJ", (".obj",), animated=False, texture=True, vertex_colors=False),
    MeshFormat("PLY", (".ply",), animated=False, texture=False, vertex_colors=True),
)
"""Every format, by suffix."""

MOTION_OPTIONS = {"motion": "--motion", "frames": "--frames", "fps": "--fps", "name_map": "--name-map",
                  "bvh_scale": "--bvh-scale", "bvh_up": "--bvh-up", "grown_rotations": "--grown-rotations"}
"""The options that only an animated format uses (parsed name -> flag)."""


def _suffixes_text() -> str:
    return ", ".join(suffix for mesh_format in MESH_FORMATS for suffix in mesh_format.suffixes)


def mesh_format_for(path: Path, *, flag: str = "-o") -> MeshFormat:
    """The format of ``path``, by the ending of its name (any case).

    Raises:
        ValueError: no format writes that suffix (the message names it and the known ones).
    """
    suffix = path.suffix.lower()
    for mesh_format in MESH_FORMATS:
        if suffix in mesh_format.suffixes:
            return mesh_format
    ending = f"{path.suffix!r} files" if path.suffix else "files without a suffix"
    raise ValueError(f"{flag} {path}: no mesh format writes {ending}; give a name ending in one of "
                     f"{_suffixes_text()}")


def _count(text: str, *, low: int, high: int) -> int:
    value = int(text)
    if not low <= value <= high:
        raise argparse.ArgumentTypeError(f"{text} is outside {low}..{high}")
    return value


def _triangle_count(text: str) -> int:
    return _count(text, low=100, high=10_000_000)


def _texture_size(text: str) -> int:
    return _count(text, low=64, high=16384)


def _view_count(text: str) -> int:
    return _count(text, low=4, high=1024)


def _view_size(text: str) -> int:
    return _count(text, low=32, high=4096)


for _function, _name in ((_triangle_count, "triangle count"), (_texture_size, "texture size"),
                         (_view_count, "view count"), (_view_size, "view size")):
    _function.__name__ = _name  # argparse's message: "invalid triangle count value: 'x'"


def build_parser() -> argparse.ArgumentParser:
    """The ``warpavatar-export`` parser: ``--help`` shows the main options and :data:`EXAMPLES`, ``--help-all``
    every option by group."""
    parser = ArgumentParser(prog="warpavatar-export", description=DESCRIPTION, add_help=False,
                            usage="%(prog)s AVATAR -o FILE [--motion M] [--triangles N] [--texture-size S] [options]",
                            formatter_class=argparse.RawDescriptionHelpFormatter)
    main = parser.add_argument_group(MAIN_GROUP)
    main.add_argument("avatar", type=Path, help="the fit's output folder (or its avatar.pt)")
    main.add_argument("-o", "--output", required=True, type=Path, metavar="FILE",
                      help="the file to write; its suffix chooses the format: .glb (binary) or .gltf (JSON, "
                           "buffers and texture embedded) for glTF 2.0; .usdc or .usd (binary crate), .usda (text), "
                           "each with FILE's stem.texture.png beside it, or .usdz (one package holding the texture) "
                           "for a UsdSkel skinned mesh; .obj (the rest pose, textured: FILE's stem.mtl and "
                           "stem.texture.png beside it) or .ply (the rest pose with vertex colours, binary) for a "
                           "static mesh, Y-up as glTF. Existing files are replaced once the new ones are complete")
    main.add_argument("--triangles", type=_triangle_count, default=None, metavar="N",
                      help=f"triangles of the mesh, after decimation [triangles] (default: {DEFAULT_TRIANGLES})")
    main.add_argument("--texture-size", type=_texture_size, default=None, metavar="S",
                      help="width and height of the texture atlas [px]; not for .ply, which holds vertex colours "
                           f"(default: {DEFAULT_TEXTURE_SIZE})")
    add_motion_arguments(main, default=TRAINING_MOTION_HELP + "; .obj and .ply take no motion")
    main.add_argument("--device", default=default_device(),
                      help="torch device: cpu, cuda or cuda:N (default: %(default)s, cuda where torch sees a GPU)")
    main.add_argument("--no-progress", action="store_true", help="hide the progress bar (default: shown)")
    shown = {"avatar", "output", "triangles", "texture_size", "motion", "frames", "fps", "device", "no_progress"}
    retarget = parser.add_argument_group("motions of other skeletons")
    for action in list(main._group_actions):
        if action.dest in shown:
            main_option(action)
        elif action.dest in MOTION_OPTIONS:  # the BVH and grown-joint options: in a group of their own
            main._group_actions.remove(action)
            retarget._group_actions.append(action)
    research = parser.add_argument_group("research: the renders the mesh is made from")
    research.add_argument("--view-count", type=_view_count, default=DEFAULT_VIEW_COUNT, metavar="N",
                          help="renders of the rest pose all around the avatar, which the surface is fused from and "
                               "the colours baked from [views] (default: %(default)s)")
    research.add_argument("--view-size", type=_view_size, default=DEFAULT_VIEW_SIZE, metavar="PX",
                          help="width and height of each render [px] (default: %(default)s)")
    add_help_options(main, summary=SUMMARY, examples=EXAMPLES, part_groups=False)
    return parser


@friendly_errors
def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    check_output_path(args.output, "-o", folder=False)
    mesh_format = mesh_format_for(args.output)
    check_options(args, mesh_format)
    outputs = [args.output] + companion_paths(args.output, mesh_format)
    for path in outputs[1:]:
        check_output_path(path, "-o", folder=False)
    with contextlib.ExitStack() as locks:
        for path in outputs:
            locks.enter_context(output_lock(path, flag="-o"))
        return export(args, mesh_format=mesh_format)


def check_options(args: argparse.Namespace, mesh_format: MeshFormat) -> None:
    """Refuse options ``mesh_format`` would not use: a motion's for a static format, ``--texture-size`` for one
    without a texture.

    Raises:
        ValueError: naming ``-o``, its format and the options given.
    """
    unused = [] if mesh_format.animated else [flag for name, flag in MOTION_OPTIONS.items()
                                              if getattr(args, name) is not None]
    if args.texture_size is not None and not mesh_format.texture:
        unused.append("--texture-size")
    if unused:
        what = [] if mesh_format.animated else ["is a static mesh (the rest pose, no motion)"]
        what += [] if mesh_format.texture else ["holds vertex colours, no texture"]
        raise ValueError(f"-o {args.output}: {mesh_format.name} {' and '.join(what)}, so {', '.join(unused)} would "
                         f"not be used; leave {'it' if len(unused) == 1 else 'them'} out, or give -o the suffix of "
                         f"another format ({_suffixes_text()})")


def _obj_stem(output: Path) -> str:
    """The name an .obj's material library and texture start with: its own stem, with any character but letters,
    digits, ``.``, ``_`` and ``-`` replaced by ``_`` (OBJ readers split ``mtllib`` and ``map_Kd`` at spaces)."""
    return re.sub(r"[^A-Za-z0-9._-]", "_", output.stem)


def companion_paths(output: Path, mesh_format: MeshFormat) -> list[Path]:
    """The files written beside ``output``: an .obj's material library and texture (``STEM.mtl``,
    ``STEM.texture.png``), the texture of a .usd / .usdc / .usda (``STEM.texture.png``; a .usdz holds its own)."""
    if mesh_format.name == "OBJ":
        stem = _obj_stem(output)
        return [output.with_name(f"{stem}.mtl"), output.with_name(f"{stem}.texture.png")]
    if mesh_format.name == "UsdSkel" and output.suffix.lower() != ".usdz":
        return [output.with_name(f"{output.stem}.texture.png")]
    return []


def export(args: argparse.Namespace, *, mesh_format: MeshFormat) -> int:
    """Write the output of ``main``'s parsed arguments in ``mesh_format`` (its outputs locked); the exit status."""
    from warpavatar.cli.common import resolve_device
    from warpavatar.io.exporters import ExportMotion
    from warpavatar.mesh.build import build_avatar_mesh, recorded_pixel_size, recorded_training_motion

    device = resolve_device(args.device)
    avatar = load_avatar(args)
    motion = None
    if mesh_format.animated:  # read before the mesh is made, so that a bad motion fails at once
        loaded, _, part_inputs = load_motion_for(avatar, args)
        motion = ExportMotion.from_motion(loaded, fps=args.fps, part_inputs=part_inputs)
    start = time.time()
    mesh = build_avatar_mesh(avatar, triangles=args.triangles or DEFAULT_TRIANGLES,
                             texture_size=args.texture_size or DEFAULT_TEXTURE_SIZE, view_count=args.view_count,
                             view_size=args.view_size, training_pixel_size=recorded_pixel_size(args.avatar),
                             training_motion=recorded_training_motion(args.avatar, avatar.skeleton),
                             device=device, texture=mesh_format.texture,
                             vertex_colors=mesh_format.vertex_colors, skin=mesh_format.animated,
                             progress=not args.no_progress)
    args.output.parent.mkdir(parents=True, exist_ok=True)
    details = [f"{mesh.vertex_count} vertices", f"{mesh.face_count} triangles"]
    if mesh_format.animated:
        from warpavatar.mesh.skin import mesh_animation

        animation = mesh_animation(avatar, mesh, motion, progress=not args.no_progress)
        details += [f"{len(mesh.joint_names)} joints", f"{animation.frame_count} frames at {animation.fps:g} fps"]
        details += write_animated(args.output, mesh, animation)
    elif mesh_format.name == "OBJ":
        write_obj(args.output, mesh)
        details.append(f"{mesh.texture.shape[1]}x{mesh.texture.shape[0]} texture")
    else:
        write_ply(args.output, mesh)
    size = sum(path.stat().st_size for path in [args.output] + companion_paths(args.output, mesh_format)
               if path.exists())
    details.append(f"{size / 2**20:.1f} MiB")
    print(f"wrote {args.output} ({', '.join(details)}) in {time.time() - start:.1f} s")
    return 0


def write_animated(path: Path, mesh, animation) -> list[str]:
    """Write the skinned ``mesh`` with ``animation`` as glTF 2.0 or UsdSkel, by the suffix of ``path``; a few
    words on how the motion beyond skinning was written, for the ``wrote`` line (none without one)."""
    if path.suffix.lower() in (".glb", ".gltf"):
        from warpavatar.io.gltf import write_gltf

        written = write_gltf(path, mesh, animation)
        if not written.morph_target_count:
            return []
        return [f"{written.morph_target_count} morph targets for the offsets beyond skinning (largest error "
                f"{written.morph_error_max * 1000:.1f} mm)"]
    from warpavatar.io.usd_mesh import write_usd_mesh

    written = write_usd_mesh(path, mesh, animation)
    return ["points time-sampled for the offsets beyond skinning"] if written.vertex_cache else []


def _trimesh(mesh, *, texture: bool, name: str):
    """``mesh`` as a ``trimesh.Trimesh`` turned Y-up (as glTF is, and as OBJ and PLY readers assume), with its
    normals and either its texture (``texture``) or its vertex colours."""
    import numpy as np
    import trimesh

    from warpavatar.io.gltf import up_to_y_rotation

    axes = up_to_y_rotation(mesh.up)
    vertices = (np.asarray(mesh.vertices, dtype=np.float64) @ axes.T).astype(np.float32)
    normals = (np.asarray(mesh.normals, dtype=np.float64) @ axes.T).astype(np.float32)
    visual = None
    if texture:
        from PIL import Image
        from trimesh.visual import TextureVisuals
        from trimesh.visual.material import SimpleMaterial

        uvs = np.column_stack([mesh.uvs[:, 0], 1.0 - mesh.uvs[:, 1]])  # OBJ's v counts up from the image's bottom
        material = SimpleMaterial(name=name, image=Image.fromarray(mesh.texture), ambient=[255, 255, 255, 255],
                                  diffuse=[255, 255, 255, 255], specular=[0, 0, 0, 255], glossiness=1.0)
        visual = TextureVisuals(uv=uvs, material=material)
    return trimesh.Trimesh(vertices, mesh.faces, vertex_normals=normals, visual=visual,
                           vertex_colors=None if texture else mesh.vertex_colors, process=False)


def write_obj(path: Path, mesh) -> None:
    """Write the textured rest-pose ``mesh`` (Y-up) as Wavefront OBJ at ``path``, with its material library and
    texture beside it (:func:`companion_paths`); each file atomically, all three renamed into place only once
    every one is complete."""
    import trimesh

    from warpavatar.io.output_files import atomic_path

    mtl_path, png_path = companion_paths(path, MESH_FORMATS[2])
    material = png_path.name.removesuffix(".png")  # trimesh names the texture after the material
    text, files = trimesh.exchange.obj.export_obj(_trimesh(mesh, texture=True, name=material), include_normals=True,
                                                  include_color=False, return_texture=True, mtl_name=mtl_path.name,
                                                  header="warpavatar-export")
    if set(files) != {mtl_path.name, png_path.name}:
        raise OSError(f"-o {path}: trimesh named the .obj's files {sorted(files)}, not {mtl_path.name} and "
                      f"{png_path.name}")
    with atomic_path(png_path) as png, atomic_path(mtl_path) as mtl, atomic_path(path) as obj:
        png.write_bytes(files[png_path.name])
        mtl.write_bytes(files[mtl_path.name])
        obj.write_text(text, encoding="utf-8")


def write_ply(path: Path, mesh) -> None:
    """Write the rest-pose ``mesh`` (Y-up) with its vertex colours and normals as a binary PLY at ``path``,
    atomically."""
    from warpavatar.io.output_files import write_bytes_atomic

    data = _trimesh(mesh, texture=False, name=path.stem).export(file_type="ply", encoding="binary",
                                                                 vertex_normal=True)
    write_bytes_atomic(path, data)


if __name__ == "__main__":
    sys.exit(main())
