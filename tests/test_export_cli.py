"""warpavatar-export on a small avatar at tiny settings: each format is written and read back by another library
(trimesh for .glb, .obj and .ply, usd-core for .usdc and .usdz), and bad input is one line, exit status 2, with
nothing left behind."""

import errno
import json
import shutil
import struct
import types
from pathlib import Path

import numpy as np
import pytest
import torch

from warpavatar import data
from warpavatar.cli import export
from warpavatar.fit.outputs import TRAINING_MOTION_NAME, write_training_motion

TINY = ["--triangles", "2000", "--texture-size", "256", "--view-count", "12", "--view-size", "96", "--no-progress",
        "--device", "cpu"]
TINY_STATIC = [word for word in TINY if word not in ("--texture-size", "256")]
TRAINING_FRAMES = 5


@pytest.fixture(scope="module")
def fitted(avatar_dir, tmp_path_factory):
    """The small avatar in a folder of its own, with a training motion of the first demo frames beside it (as a
    fit leaves them)."""
    folder = tmp_path_factory.mktemp("export_avatar")
    shutil.copy(avatar_dir / "avatar.pt", folder / "avatar.pt")
    video = data.load_video_folder(data.demo_subject_path() / "train", max_frames=TRAINING_FRAMES)
    frames = types.SimpleNamespace(bone_transforms=torch.as_tensor(video.bone_transforms), frame_ids=video.frame_ids,
                                   video=video)
    write_training_motion(frames, folder / TRAINING_MOTION_NAME)
    return folder


def _run(capsys, *argv) -> tuple[int, str, str]:
    code = export.main([str(word) for word in argv])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def _wrote_line(out: str, path: Path) -> str:
    (line,) = [line for line in out.splitlines() if line.startswith(f"wrote {path} (")]
    return line


def _leftovers(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if ".tmp-" in p.name or p.name.endswith(".warpavatar-lock"))


def _glb_json(path: Path) -> dict:
    blob = path.read_bytes()
    magic, version, length = struct.unpack_from("<4sII", blob, 0)
    assert (magic, version, length) == (b"glTF", 2, len(blob))
    chunk_length, chunk_type = struct.unpack_from("<I4s", blob, 12)
    assert chunk_type == b"JSON"
    return json.loads(blob[20:20 + chunk_length])


@pytest.mark.parametrize("suffix", [".glb", ".gltf"])
def test_gltf_holds_the_skinned_textured_mesh_and_the_training_motion(fitted, tmp_path, capsys, suffix):
    import trimesh

    output = tmp_path / f"avatar{suffix}"
    code, out, err = _run(capsys, fitted, "-o", output, *TINY)
    assert code == 0, err
    line = _wrote_line(out, output)
    assert f"{TRAINING_FRAMES} frames" in line and " joints" in line and "MiB" in line
    document = _glb_json(output) if suffix == ".glb" else json.loads(output.read_text())
    assert sorted(p.name for p in tmp_path.iterdir()) == [output.name]  # buffers and texture inside
    assert len(document["skins"]) == 1 and len(document["animations"]) == 1
    assert len(document["images"]) == 1 and document["meshes"][0]["primitives"][0]["attributes"]["TEXCOORD_0"] >= 0
    scene = trimesh.load(output)
    (geometry,) = scene.geometry.values()
    assert 500 <= len(geometry.faces) <= 2600
    assert f"{len(geometry.faces)} triangles" in line
    assert _leftovers(tmp_path) == []


@pytest.mark.parametrize("suffix", [".usdc", ".usdz"])
def test_usd_holds_a_usdskel_mesh_with_the_motion(fitted, tmp_path, capsys, suffix):
    from pxr import Usd, UsdGeom, UsdSkel

    motion = data.demo_subject_path() / "novel_pose" / "dance_cam000"
    output = tmp_path / f"dance{suffix}"
    code, out, err = _run(capsys, fitted, "-o", output, "--motion", motion, "--frames", "1:4", *TINY)
    assert code == 0, err
    line = _wrote_line(out, output)
    assert "3 frames" in line
    stage = Usd.Stage.Open(str(output))
    meshes = [prim for prim in stage.Traverse() if prim.IsA(UsdGeom.Mesh)]
    skeletons = [prim for prim in stage.Traverse() if prim.IsA(UsdSkel.Skeleton)]
    animations = [prim for prim in stage.Traverse() if prim.IsA(UsdSkel.Animation)]
    assert len(meshes) == 1 and len(skeletons) == 1 and len(animations) == 1
    counts = UsdGeom.Mesh(meshes[0]).GetFaceVertexCountsAttr().Get()
    assert f"{len(counts)} triangles" in line and set(counts) == {3}
    binding = UsdSkel.BindingAPI(meshes[0])
    assert binding.GetJointIndicesPrimvar().GetElementSize() == 4
    rotations = UsdSkel.Animation(animations[0]).GetRotationsAttr()
    assert len(rotations.GetTimeSamples()) == 3
    assert _leftovers(tmp_path) == []


def test_obj_is_the_textured_rest_pose_with_its_material_and_texture(fitted, tmp_path, capsys):
    import trimesh

    output = tmp_path / "avatar.obj"
    code, out, err = _run(capsys, fitted, "-o", output, *TINY)
    assert code == 0, err
    line = _wrote_line(out, output)
    assert "256x256 texture" in line and "joints" not in line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["avatar.mtl", "avatar.obj", "avatar.texture.png"]
    assert "map_Kd avatar.texture.png" in (tmp_path / "avatar.mtl").read_text()
    mesh = trimesh.load(output, process=False)
    assert isinstance(mesh.visual, trimesh.visual.TextureVisuals)
    assert mesh.visual.uv.shape == (len(mesh.vertices), 2) and 0.0 <= mesh.visual.uv.min() <= mesh.visual.uv.max() <= 1
    assert mesh.visual.material.image.size == (256, 256)
    assert f"{len(mesh.faces)} triangles" in line and f"{len(mesh.vertices)} vertices" in line
    # Y-up: the demo skeleton stands 1.25 m tall along +Z, and is 0.2 m deep along Y (its front towards -Y)
    assert mesh.vertices[:, 1].max() > 0.9 and np.abs(mesh.vertices[:, 2]).max() < 0.5
    assert _leftovers(tmp_path) == []


def test_ply_is_the_rest_pose_with_vertex_colours(fitted, tmp_path, capsys):
    import trimesh

    output = tmp_path / "avatar.ply"
    code, out, err = _run(capsys, fitted, "-o", output, *TINY_STATIC)
    assert code == 0, err
    line = _wrote_line(out, output)
    assert output.read_bytes().startswith(b"ply\nformat binary_little_endian 1.0\n")
    mesh = trimesh.load(output, process=False)
    assert f"{len(mesh.faces)} triangles" in line and f"{len(mesh.vertices)} vertices" in line
    colours = mesh.visual.vertex_colors[:, :3]
    assert len(np.unique(colours, axis=0)) > 10  # baked colours, not one default
    assert mesh.is_winding_consistent
    assert _leftovers(tmp_path) == []


def _bad_motion(tmp_path: Path) -> Path:
    path = tmp_path / "inputs" / "bad.npz"
    path.parent.mkdir()
    np.savez(path, bone_transforms=np.tile(np.eye(4, dtype=np.float32), (3, 5, 1, 1)))
    return path


@pytest.mark.parametrize("case, expected", [
    ("suffix", "no mesh format writes '.abc' files; give a name ending in one of .glb, .gltf, .usd, .usdc, .usda, "
               ".usdz, .obj, .ply"),
    ("missing avatar", "no avatar file here"),
    ("bad motion", "bad.npz"),
    ("static with motion", "is a static mesh (the rest pose, no motion), so --motion would not be used"),
    ("ply with texture size", "holds vertex colours, no texture, so --texture-size would not be used"),
    ("no training motion", "no such file, so there is no training motion to default to"),
])
def test_bad_input_is_one_line_and_leaves_nothing(fitted, avatar_dir, tmp_path, capsys, case, expected):
    out_folder = tmp_path / "out"
    out_folder.mkdir()
    argv = {"suffix": [fitted, "-o", out_folder / "x.abc"],
            "missing avatar": [tmp_path / "nowhere", "-o", out_folder / "x.glb"],
            "bad motion": [fitted, "-o", out_folder / "x.glb", "--motion", _bad_motion(tmp_path)],
            "static with motion": [fitted, "-o", out_folder / "x.obj", "--motion", fitted / TRAINING_MOTION_NAME],
            "ply with texture size": [fitted, "-o", out_folder / "x.ply", "--texture-size", "64"],
            "no training motion": [avatar_dir, "-o", out_folder / "x.usdc"]}[case]
    code, out, err = _run(capsys, *argv, "--no-progress", "--device", "cpu")
    assert code == 2
    assert len(err.strip().splitlines()) == 1 and err.startswith("error: ") and expected in err, err
    assert list(out_folder.iterdir()) == []


def test_bad_option_values_are_usage_errors(fitted, tmp_path, capsys):
    for option, value in (("--triangles", "10"), ("--texture-size", "x"), ("--view-count", "0")):
        with pytest.raises(SystemExit) as exit_info:
            export.main([str(fitted), "-o", str(tmp_path / "x.glb"), option, value])
        assert exit_info.value.code == 2
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and option in err
    assert list(tmp_path.iterdir()) == []


def test_a_failed_obj_write_leaves_the_earlier_files(fitted, tmp_path, capsys, monkeypatch):
    """The .obj, .mtl and .png are renamed into place only once all three are complete: a full disk while writing
    them is one line, and the earlier export's files stay as they were, with no temporary file left."""
    earlier = {name: f"earlier {name}".encode() for name in ("avatar.obj", "avatar.mtl", "avatar.texture.png")}
    for name, content in earlier.items():
        (tmp_path / name).write_bytes(content)
    original = Path.write_text

    def full_disk(self, *args, **kwargs):
        if ".tmp-" in self.name:
            raise OSError(errno.ENOSPC, "No space left on device", str(self))
        return original(self, *args, **kwargs)

    monkeypatch.setattr(Path, "write_text", full_disk)
    code, out, err = _run(capsys, fitted, "-o", tmp_path / "avatar.obj", *TINY)
    assert code == 2 and "no space is left on the disk" in err and len(err.strip().splitlines()) == 1
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == earlier


def test_help_gives_each_option_its_default_and_the_research_knobs_in_help_all(capsys):
    with pytest.raises(SystemExit):
        export.main(["--help"])
    short = capsys.readouterr().out
    assert "--triangles N" in short and "(default: 50000)" in short and "(default: 1024)" in short
    assert "--view-count" not in short and "warpavatar-export warpavatar-out/demo -o avatar.glb" in short
    with pytest.raises(SystemExit):
        export.main(["--help-all"])
    every = capsys.readouterr().out
    assert "--view-count N" in every and "--bvh-scale" in every and ".mtl" in every
