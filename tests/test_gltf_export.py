"""Skin weights and motion of the avatar's mesh (warpavatar.mesh.skin) and its glTF 2.0 files (warpavatar.io.gltf):
read back, the files pose the mesh as the project's own skinning does, their morph targets reproduce the vertex
offsets within the tolerance with weights in [0, 1], three.js's GLTFLoader reads their sparse targets, and Khronos'
glTF-Validator finds no error and no warning in them."""

import base64
import dataclasses
import json
import os
import shutil
import struct
import subprocess
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from warpavatar.io.gltf import (GENERATOR, MORPH_TOLERANCE, morph_targets, rotation_quaternions,
                                up_to_y_rotation, write_gltf)
from warpavatar.mesh import AvatarMesh, MeshAnimation
from warpavatar.mesh.skin import OFFSET_TOLERANCE, lbs_vertices, mesh_animation, skin_mesh, top_influences
from warpavatar.model import Avatar

from conftest import body_mesh, sway_part

NODE_MODULES = Path(os.environ.get("WARPAVATAR_NODE_MODULES",
                                   Path.home() / ".cache" / "warpavatar-node" / "node_modules"))
POSE_TOLERANCE = 1e-4  # [m]


# --------------------------------------------------------------------------------------------------- fixtures
def garment_offsets(mesh: AvatarMesh, frame_count: int) -> np.ndarray:
    """Offsets [T,V,3] [m] of a skirt: the lowest 30 % of the vertices along the mesh's up, two smooth patterns
    (a swirl and a flare, growing towards the hem) with amplitudes of both signs over the frames."""
    up = np.asarray(mesh.up, dtype=np.float64) / np.linalg.norm(mesh.up)
    height = np.asarray(mesh.vertices, dtype=np.float64) @ up
    waist = np.quantile(height, 0.3)
    skirt = height < waist
    depth = np.where(skirt, (waist - height) / (waist - height.min()), 0.0)
    side = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    side /= np.linalg.norm(side)
    across = np.cross(up, side)
    centred = np.asarray(mesh.vertices, dtype=np.float64) - np.asarray(mesh.vertices).mean(0)
    angle = np.arctan2(centred @ across, centred @ side)
    radial = np.cos(angle)[:, None] * side + np.sin(angle)[:, None] * across
    swirl = depth[:, None] * (np.sin(2 * angle)[:, None] * side + np.cos(2 * angle)[:, None] * across)
    flare = np.square(depth)[:, None] * radial
    phase = np.linspace(0.0, 2.0 * np.pi, frame_count, endpoint=False)
    offsets = 0.03 * np.sin(phase + 0.4)[:, None, None] * swirl + 0.02 * np.cos(2 * phase)[:, None, None] * flare
    return offsets.astype(np.float32)


def grown_avatar(avatar_dir, motion) -> Avatar:
    """The fixture's avatar with two joints grown on the skeleton (ToMiE's extra joints)."""
    from warpavatar.extensions.joint_growth import ExtraJoints

    avatar = Avatar.load(avatar_dir / "avatar.pt")
    names = avatar.skeleton.names
    parents = torch.tensor([names.index("Hips"), names.index("LowerArmL")])
    heads = torch.as_tensor(avatar.skeleton.heads)[parents]
    bones = torch.as_tensor(motion.bone_transforms)
    part = ExtraJoints(parents, heads, bones, torch.arange(bones.shape[0]).float() / 30.0, extent=1.0,
                       hidden_position=8, hidden_rotation=8, layers=1)
    avatar.field.add_joints(parents)
    avatar.add_part(part)
    return avatar


# ------------------------------------------------------------------------------------------- reading a file
COMPONENTS = {5121: np.uint8, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}
WIDTHS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}


def read_gltf(path: Path) -> tuple[dict, bytes]:
    raw = path.read_bytes()
    if raw[:4] == b"glTF":
        magic, version, total = struct.unpack_from("<III", raw, 0)
        assert version == 2 and total == len(raw) and total % 4 == 0
        json_length, json_kind = struct.unpack_from("<II", raw, 12)
        doc = json.loads(raw[20:20 + json_length])
        bin_length, bin_kind = struct.unpack_from("<II", raw, 20 + json_length)
        assert bin_kind == 0x004E4942 and json_length % 4 == 0 and bin_length % 4 == 0
        return doc, raw[28 + json_length:28 + json_length + bin_length]
    doc = json.loads(raw)
    uri = doc["buffers"][0]["uri"]
    assert uri.startswith("data:application/octet-stream;base64,")
    return doc, base64.b64decode(uri.partition(",")[2])


def view_values(doc: dict, blob: bytes, reference: dict, component: int, count: int) -> np.ndarray:
    view = doc["bufferViews"][reference["bufferView"]]
    start = view.get("byteOffset", 0) + reference.get("byteOffset", 0)
    return np.frombuffer(blob, dtype=COMPONENTS[component], count=count, offset=start)


def accessor(doc: dict, blob: bytes, index: int) -> np.ndarray:
    """An accessor's values (a sparse one's substituted into its base, zeros without a buffer view)."""
    entry = doc["accessors"][index]
    width = WIDTHS[entry["type"]]
    dtype = COMPONENTS[entry["componentType"]]
    if "bufferView" in entry:
        values = view_values(doc, blob, entry, entry["componentType"], entry["count"] * width)
    else:
        values = np.zeros(entry["count"] * width, dtype)
    sparse = entry.get("sparse")
    if sparse is not None:
        rows = view_values(doc, blob, sparse["indices"], sparse["indices"]["componentType"], sparse["count"])
        assert (np.diff(rows.astype(np.int64)) > 0).all()  # strictly increasing, as the specification asks
        values = values.copy().reshape(entry["count"], width)
        values[rows] = view_values(doc, blob, sparse["values"], entry["componentType"],
                                   sparse["count"] * width).reshape(-1, width)
        values = values.reshape(-1)
    values = values.reshape(entry["count"], width) if width > 1 else values
    if entry.get("normalized"):
        values = values / np.iinfo(dtype).max
    return values


def quaternion_matrix(q) -> np.ndarray:
    x, y, z, w = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def posed_from_file(doc: dict, blob: bytes, frame: int) -> np.ndarray:
    """The file's mesh vertices at keyframe ``frame``, as a glTF player computes them: animated node TRS ->
    world matrices -> skin matrices -> morph targets, then linear blend skinning."""
    nodes = doc["nodes"]
    trs = [{"translation": np.array(n.get("translation", [0.0, 0.0, 0.0]), float),
            "rotation": np.array(n.get("rotation", [0.0, 0.0, 0.0, 1.0]), float)} for n in nodes]
    morph_weights = None
    for animation in doc.get("animations", []):
        for channel in animation["channels"]:
            sampler = animation["samplers"][channel["sampler"]]
            output = accessor(doc, blob, sampler["output"])
            target = channel["target"]
            if target["path"] == "weights":
                count = len(doc["meshes"][nodes[target["node"]]["mesh"]]["primitives"][0]["targets"])
                morph_weights = output.reshape(-1, count)[frame]
            else:
                trs[target["node"]][target["path"]] = np.asarray(output[frame], float)
    parent = {child: index for index, node in enumerate(nodes) for child in node.get("children", [])}

    def world(index):
        local = np.eye(4)
        local[:3, :3] = quaternion_matrix(trs[index]["rotation"])
        local[:3, 3] = trs[index]["translation"]
        return local if index not in parent else world(parent[index]) @ local

    skin = doc["skins"][0]
    inverse_bind = np.swapaxes(accessor(doc, blob, skin["inverseBindMatrices"]).reshape(-1, 4, 4), 1, 2)
    matrices = np.stack([world(joint) for joint in skin["joints"]]) @ inverse_bind
    primitive = doc["meshes"][0]["primitives"][0]
    positions = accessor(doc, blob, primitive["attributes"]["POSITION"]).astype(float)
    if morph_weights is not None:
        for weight, target in zip(morph_weights, primitive["targets"]):
            positions = positions + weight * accessor(doc, blob, target["POSITION"])
    joints = accessor(doc, blob, primitive["attributes"]["JOINTS_0"]).astype(int)
    weights = accessor(doc, blob, primitive["attributes"]["WEIGHTS_0"]).astype(float)
    blended = (weights[:, :, None, None] * matrices[joints]).sum(1)
    return np.einsum("vij,vj->vi", blended[:, :3, :3], positions) + blended[:, :3, 3]


def assert_file_poses_like_the_project(path: Path, mesh: AvatarMesh, animation: MeshAnimation) -> dict:
    doc, blob = read_gltf(path)
    axes = up_to_y_rotation(mesh.up)
    for frame in range(animation.frame_count):
        offsets = None if animation.vertex_offsets is None else animation.vertex_offsets[frame]
        expected = lbs_vertices(mesh, animation.joint_transforms[frame], offsets) @ axes.T
        got = posed_from_file(doc, blob, frame)
        error = np.linalg.norm(got - expected, axis=1).max()
        assert error < POSE_TOLERANCE, f"frame {frame}: the file poses vertices {error:.2e} m from lbs_vertices"
    return doc


def validate(paths: list[Path]) -> None:
    """Khronos glTF-Validator (npm gltf-validator): no error, no warning (infos and hints allowed)."""
    module = NODE_MODULES / "gltf-validator"
    node = shutil.which("node")
    if node is None or not module.is_dir():
        message = (f"no node or no gltf-validator under {NODE_MODULES} (npm install --prefix "
                   f"{NODE_MODULES.parent} gltf-validator, or set WARPAVATAR_NODE_MODULES)")
        if os.environ.get("CI"):
            pytest.fail(f"{message}; CI is set, so the validator must run")
        pytest.skip(message)
    script = """
const fs = require('fs');
const validator = require(process.argv[1]);
(async () => {
  const reports = {};
  for (const file of process.argv.slice(2)) {
    const report = await validator.validateBytes(new Uint8Array(fs.readFileSync(file)), {maxIssues: 50});
    reports[file] = report.issues;
  }
  console.log(JSON.stringify(reports));
})().catch((error) => { console.error(String(error)); process.exit(1); });
"""
    result = subprocess.run([node, "-e", script, str(module), *map(str, paths)], capture_output=True, text=True,
                            timeout=120)
    assert result.returncode == 0, result.stderr
    for file, issues in json.loads(result.stdout).items():
        problems = [m for m in issues["messages"] if m["severity"] <= 1]
        assert issues["numErrors"] == 0 and issues["numWarnings"] == 0, f"{file}: {json.dumps(problems, indent=1)}"


# ------------------------------------------------------------------------------------------------------ tests
def test_skin_weights_are_the_fields_top_four(export_avatar, skinned_body):
    assert skinned_body.joint_names == export_avatar.rig().names
    assert skinned_body.joint_indices.shape == (skinned_body.vertex_count, 4)
    assert skinned_body.joint_indices.dtype == np.int32
    np.testing.assert_allclose(skinned_body.joint_weights.sum(1), 1.0, atol=1e-6)
    assert (np.diff(skinned_body.joint_weights, axis=1) <= 0).all()
    with torch.no_grad():
        field = export_avatar.field.weights(torch.as_tensor(skinned_body.vertices)).numpy()
    top = np.sort(field, axis=1)[:, ::-1][:, :4]
    np.testing.assert_allclose(skinned_body.joint_weights, top / top.sum(1, keepdims=True), atol=1e-6)
    np.testing.assert_array_equal(np.take_along_axis(field, skinned_body.joint_indices, 1), top)


def test_top_influences_pad_and_normalise():
    index, weights = top_influences(np.array([[0.2, 0.6], [1.0, 0.0]]))
    np.testing.assert_array_equal(index, [[1, 0, 0, 0], [0, 0, 0, 0]])
    np.testing.assert_allclose(weights, [[0.75, 0.25, 0, 0], [1, 0, 0, 0]], atol=1e-7)


def test_animation_has_the_avatars_skinning_transforms(export_avatar, skinned_body, export_motion):
    animation = mesh_animation(export_avatar, skinned_body, export_motion)
    np.testing.assert_array_equal(animation.frame_ids, export_motion.frame_ids)
    assert animation.fps == export_motion.fps and animation.vertex_offsets is None
    for t in range(export_motion.frame_count):
        expected = export_avatar.pose_bones(torch.as_tensor(export_motion.bone_transforms[t])).numpy()
        np.testing.assert_allclose(animation.joint_transforms[t], expected, atol=1e-6)


@pytest.mark.parametrize("suffix", [".glb", ".gltf"])
def test_file_poses_the_mesh_as_the_project_does(tmp_path, export_avatar, skinned_body, export_motion, suffix):
    animation = mesh_animation(export_avatar, skinned_body, export_motion)
    written = write_gltf(tmp_path / f"avatar{suffix}", skinned_body, animation)
    assert written.binary == (suffix == ".glb") and written.byte_count == written.path.stat().st_size
    assert written.frame_count == export_motion.frame_count and written.morph_target_count == 0
    doc = assert_file_poses_like_the_project(written.path, skinned_body, animation)
    doc, blob = read_gltf(written.path)
    assert doc["asset"] == {"version": "2.0", "generator": GENERATOR}
    primitive = doc["meshes"][0]["primitives"][0]
    attributes = primitive["attributes"]
    # with a texture, COLOR_0 (which glTF multiplies into the base colour) is left out
    assert set(attributes) == {"POSITION", "NORMAL", "TEXCOORD_0", "JOINTS_0", "WEIGHTS_0"}
    assert doc["accessors"][attributes["POSITION"]]["count"] == skinned_body.vertex_count
    assert doc["accessors"][primitive["indices"]]["count"] == 3 * skinned_body.face_count
    np.testing.assert_allclose(accessor(doc, blob, attributes["WEIGHTS_0"]).sum(1), 1.0, atol=1e-6)
    np.testing.assert_allclose(accessor(doc, blob, attributes["NORMAL"]), skinned_body.normals @ up_to_y_rotation(
        skinned_body.up).T, atol=1e-6)
    assert len(doc["skins"][0]["joints"]) == len(skinned_body.joint_names)
    assert "translation" not in doc["nodes"][0] and "rotation" not in doc["nodes"][0]
    times = accessor(doc, blob, doc["animations"][0]["samplers"][0]["input"])
    np.testing.assert_allclose(times, (export_motion.frame_ids - export_motion.frame_ids[0]) / export_motion.fps,
                               atol=1e-6)
    material = doc["materials"][0]["pbrMetallicRoughness"]
    assert material["metallicFactor"] == 0 and material["roughnessFactor"] == 1 and "baseColorTexture" in material
    validate([written.path])


def test_rest_pose_file_and_vertex_colours(tmp_path, skinned_body):
    untextured = dataclasses.replace(skinned_body, texture=None)
    written = write_gltf(tmp_path / "rest.glb", untextured)
    doc, blob = read_gltf(written.path)
    colours = accessor(doc, blob, doc["meshes"][0]["primitives"][0]["attributes"]["COLOR_0"])
    np.testing.assert_allclose(colours[:, :3] * 255, skinned_body.vertex_colors, atol=1e-4)
    assert "animations" not in doc and written.frame_count == 0
    static = write_gltf(tmp_path / "static.gltf", dataclasses.replace(skinned_body, joint_indices=None))
    assert "skins" not in read_gltf(static.path)[0]
    validate([written.path, static.path])


def test_grown_joints_are_written_and_animated(tmp_path, avatar_dir, export_motion):
    avatar = grown_avatar(avatar_dir, export_motion)
    mesh = skin_mesh(avatar, body_mesh(avatar.skeleton))
    assert mesh.joint_names[-2:] == ["grown_Hips_0", "grown_LowerArmL_1"]
    angles = np.linspace(0.0, 1.0, export_motion.frame_count)
    rotations = np.zeros((export_motion.frame_count, 2, 4), np.float32)
    rotations[:, :, 0], rotations[:, :, 1] = np.cos(angles / 2)[:, None], np.sin(angles / 2)[:, None]
    turning = dataclasses.replace(export_motion, part_inputs={"joint_growth": rotations})
    animation = mesh_animation(avatar, mesh, turning)
    assert animation.joint_transforms.shape[1] == avatar.joint_count + 2
    written = write_gltf(tmp_path / "grown.glb", mesh, animation)
    assert_file_poses_like_the_project(written.path, mesh, animation)
    validate([written.path])


def test_offsets_carry_what_parts_move_beyond_skinning(avatar_dir, export_motion):
    avatar = Avatar.load(avatar_dir / "avatar.pt")
    mesh = skin_mesh(avatar, body_mesh(avatar.skeleton))
    displacements = torch.randn(export_motion.frame_count, 3, generator=torch.Generator().manual_seed(3)) * 0.02
    avatar.add_part(sway_part(displacements))
    animation = mesh_animation(avatar, mesh, export_motion)
    assert animation.vertex_offsets.shape == (export_motion.frame_count, mesh.vertex_count, 3)
    for t in range(export_motion.frame_count):
        moved = lbs_vertices(mesh, animation.joint_transforms[t], animation.vertex_offsets[t])
        still = lbs_vertices(mesh, animation.joint_transforms[t])
        # exact where the blended 3x3 is well conditioned; damped (never larger than 5x) in LBS's folds
        rotations = animation.joint_transforms[t][mesh.joint_indices, :3, :3]
        blended = np.einsum("vk,vkij->vij", mesh.joint_weights, rotations)
        clear = np.abs(np.linalg.det(blended)) >= 0.2
        assert clear.mean() > 0.4  # enough vertices where the offset must be exact (about half on this motion)
        expected = np.broadcast_to(displacements[t].numpy(), moved.shape)
        np.testing.assert_allclose((moved - still)[clear], expected[clear], atol=1e-5)
        bound = 5.0 * np.linalg.norm(expected, axis=1) + 1e-6
        assert (np.linalg.norm(animation.vertex_offsets[t], axis=1) <= bound).all()
    avatar.add_part(sway_part(torch.full((export_motion.frame_count, 3), OFFSET_TOLERANCE / 4)))
    assert mesh_animation(avatar, mesh, export_motion).vertex_offsets is None


def three_reading(path: Path) -> dict:
    """What three.js's GLTFLoader (run in node) makes of a .glb without a texture: the first mesh's morph targets
    [K,V,3] and its morphTargetInfluences track's values [T,K]."""
    node = shutil.which("node")
    three = NODE_MODULES / "three" / "examples" / "jsm" / "loaders" / "GLTFLoader.js"
    if node is None or not three.is_file():
        message = f"no node or no three under {NODE_MODULES} (npm install --prefix {NODE_MODULES.parent} three)"
        if os.environ.get("CI"):
            pytest.fail(f"{message}; CI is set, so three.js must run")
        pytest.skip(message)
    script = """
import fs from 'fs';
const { GLTFLoader } = await import(process.argv[1]);
const bytes = fs.readFileSync(process.argv[2]);
new GLTFLoader().parse(bytes.buffer.slice(bytes.byteOffset, bytes.byteOffset + bytes.byteLength), '', (gltf) => {
  let mesh = null;
  gltf.scene.traverse((node) => { if (node.isMesh && !mesh) mesh = node; });
  const track = gltf.animations[0].tracks.find((t) => t.name.endsWith('.morphTargetInfluences'));
  console.log(JSON.stringify({relative: mesh.geometry.morphTargetsRelative,
    targets: mesh.geometry.morphAttributes.position.map((a) => Array.from(a.array)),
    weights: Array.from(track.values)}));
}, (error) => { console.error(String(error)); process.exit(1); });
"""
    result = subprocess.run([node, "--input-type=module", "-e", script, three.as_uri(), str(path)],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    found = json.loads(result.stdout)
    targets = np.asarray(found["targets"], dtype=np.float32)
    return {"relative": found["relative"], "targets": targets.reshape(targets.shape[0], -1, 3),
            "weights": np.asarray(found["weights"], dtype=np.float32).reshape(-1, targets.shape[0])}


def morph_arrays(doc: dict, blob: bytes) -> tuple[np.ndarray, np.ndarray]:
    """The file's morph targets [K,V,3] and their weights keyed at each frame [T,K]."""
    primitive = doc["meshes"][0]["primitives"][0]
    targets = np.stack([accessor(doc, blob, target["POSITION"]) for target in primitive["targets"]])
    animation = doc["animations"][0]
    channel = next(c for c in animation["channels"] if c["target"]["path"] == "weights")
    weights = accessor(doc, blob, animation["samplers"][channel["sampler"]]["output"])
    return targets, weights.reshape(-1, targets.shape[0])


@pytest.mark.parametrize("suffix", [".glb", ".gltf"])
def test_morph_targets_reproduce_the_offsets(tmp_path, export_avatar, skinned_body, export_motion, suffix):
    base = mesh_animation(export_avatar, skinned_body, export_motion)
    rng = np.random.default_rng(0)
    # two spatial patterns whose amplitudes over the 5 frames take both signs: two principal components, each
    # split into a positive and a negative target (4 targets, fewer than one a frame)
    patterns = rng.normal(0.0, 0.01, (2, skinned_body.vertex_count, 3))
    amplitudes = np.array([[1.0, -1.0, 1.0, -1.0, 0.0], [1.0, 1.0, -1.0, -1.0, 0.5]]).T * [2.0, 1.0]
    offsets = np.einsum("tk,kvc->tvc", amplitudes, patterns).astype(np.float32)
    animation = dataclasses.replace(base, vertex_offsets=offsets)
    written = write_gltf(tmp_path / f"morph{suffix}", skinned_body, animation)
    assert written.morph_target_count == 4 and written.morph_error_max < 1e-5 and written.morph_within_tolerance
    assert written.morph_sparse_count == 0  # every vertex moves
    doc = assert_file_poses_like_the_project(written.path, skinned_body, animation)
    assert doc["meshes"][0]["extras"]["targetNames"] == [f"offset_component_{k}_{side}" for k in range(2)
                                                         for side in ("positive", "negative")]
    targets, weights = morph_arrays(*read_gltf(written.path))
    assert targets.shape == (4, skinned_body.vertex_count, 3) and weights.min() >= 0.0 and weights.max() == 1.0
    validate([written.path])


def test_garment_targets_are_sparse_and_three_reads_them(tmp_path, export_avatar, skinned_body, export_motion,
                                                         monkeypatch):
    skinned_body = dataclasses.replace(skinned_body, texture=None)  # GLTFLoader decodes images only in a browser
    animation = dataclasses.replace(mesh_animation(export_avatar, skinned_body, export_motion),
                                    vertex_offsets=garment_offsets(skinned_body, export_motion.frame_count))
    moving = int((np.abs(animation.vertex_offsets).max((0, 2)) > 0).sum())
    assert 0.25 < moving / skinned_body.vertex_count < 0.35
    written = write_gltf(tmp_path / "garment.glb", skinned_body, animation)
    assert 0 < written.morph_target_count < export_motion.frame_count and written.morph_within_tolerance
    assert written.morph_sparse_count == written.morph_target_count
    doc = assert_file_poses_like_the_project(written.path, skinned_body, animation)
    for target in doc["meshes"][0]["primitives"][0]["targets"]:
        entry = doc["accessors"][target["POSITION"]]
        assert "bufferView" not in entry and entry["sparse"]["count"] <= moving
    targets, weights = morph_arrays(*read_gltf(written.path))
    three = three_reading(written.path)
    assert three["relative"]  # three adds the targets to the rest positions, as glTF does
    np.testing.assert_array_equal(three["targets"], targets)
    np.testing.assert_array_equal(three["weights"], weights)
    monkeypatch.setattr("warpavatar.io.gltf.SPARSE_SHARE", -1.0)  # every target dense
    dense = write_gltf(tmp_path / "dense.glb", skinned_body, animation)
    assert dense.morph_sparse_count == 0 and written.byte_count < dense.byte_count
    np.testing.assert_array_equal(morph_arrays(*read_gltf(dense.path))[0], targets)
    validate([written.path, dense.path])


def decaying_offsets(frame_count=40, vertex_count=300, seed=1) -> np.ndarray:
    """Offsets [T,V,3] [m] of 8 patterns whose amplitudes fall by 0.3 from 10 mm, each pattern's largest vertex
    displacement 1, the amplitudes smooth in time with both signs."""
    rng = np.random.default_rng(seed)
    patterns = rng.normal(0.0, 1.0, (8, vertex_count, 3))
    patterns /= np.linalg.norm(patterns, axis=-1).max(1)[:, None, None]
    times = np.arange(frame_count) / 30.0
    amplitudes = 0.01 * 0.3 ** np.arange(8) * np.sin(2 * np.pi * rng.uniform(0.5, 2.0, 8) * times[:, None]
                                                        + rng.uniform(0, 2 * np.pi, 8))
    return np.einsum("tk,kvc->tvc", amplitudes, patterns).astype(np.float32)


def test_morph_targets_keep_the_largest_error_within_the_tolerance():
    offsets = decaying_offsets()
    morph = morph_targets(offsets)
    rebuilt = np.einsum("tk,kvc->tvc", morph.weights, morph.targets)
    error = np.linalg.norm(rebuilt - offsets, axis=-1)
    assert morph.within_tolerance and error.max() <= MORPH_TOLERANCE
    assert morph.error_max == pytest.approx(error.max(), rel=1e-3, abs=1e-9)
    assert morph.weights.min() >= 0.0 and morph.weights.max() <= 1.0 and (morph.weights.max(0) == 1.0).all()
    assert all(name.startswith("offset_component_") for name in morph.names)
    assert 0 < morph.count < offsets.shape[0]
    # fewer components leave more than the tolerance: the count is the fewest (the last kept, both its signs,
    # removed)
    component = morph.names[-1].rsplit("_", 1)[0]
    fewer = [k for k, name in enumerate(morph.names) if not name.startswith(component + "_")]
    rebuilt_fewer = np.einsum("tk,kvc->tvc", morph.weights[:, fewer], morph.targets[fewer])
    assert np.linalg.norm(rebuilt_fewer - offsets, axis=-1).max() > MORPH_TOLERANCE
    assert morph_targets(offsets, tolerance=10 * MORPH_TOLERANCE).count < morph.count
    # halfway between frames, the weights' linear blend is the offsets' (the split keeps linear playback)
    halfway = np.einsum("tk,kvc->tvc", 0.5 * (morph.weights[1:] + morph.weights[:-1]), morph.targets)
    assert np.linalg.norm(halfway - 0.5 * (offsets[1:] + offsets[:-1]), axis=-1).max() <= MORPH_TOLERANCE


def test_morph_targets_one_a_frame_or_capped(tmp_path, skinned_body, export_avatar, export_motion):
    rng = np.random.default_rng(2)
    noise = rng.normal(0.0, 0.01, (12, 100, 3)).astype(np.float32)  # every frame its own pattern
    noise[4] = 0.0  # a frame without offsets needs no target
    morph = morph_targets(noise)
    assert morph.count == 11 and morph.names == [f"offset_frame_{t}" for t in range(12) if t != 4]
    np.testing.assert_array_equal(morph.weights, np.delete(np.eye(12, dtype=np.float32), 4, axis=1))
    assert morph.error_max == 0.0 and morph.within_tolerance
    capped = morph_targets(noise, max_targets=4)
    assert capped.count <= 4 and not capped.within_tolerance and capped.error_max > MORPH_TOLERANCE
    assert capped.weights.min() >= 0.0 and capped.weights.max() <= 1.0
    offsets = rng.normal(0.0, 0.01, (export_motion.frame_count, skinned_body.vertex_count, 3)).astype(np.float32)
    animation = dataclasses.replace(mesh_animation(export_avatar, skinned_body, export_motion), vertex_offsets=offsets)
    with pytest.warns(UserWarning, match="more than the 0.20 mm tolerance") as caught:
        written = write_gltf(tmp_path / "capped.glb", skinned_body, animation, max_morph_targets=2)
    assert len(caught) == 1 and not written.morph_within_tolerance and written.morph_target_count <= 2
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert write_gltf(tmp_path / "exact.glb", skinned_body, animation).morph_within_tolerance


def test_morph_targets_of_one_sign_still_vertices_and_bad_input():
    rng = np.random.default_rng(3)
    pattern = rng.normal(0.0, 0.01, (50, 3))
    pattern[:20] = 0.0
    pattern[20:25] = 1e-7  # below a hundredth of the tolerance: still
    offsets = (np.linspace(0.2, 1.0, 6)[:, None, None] * pattern).astype(np.float32)  # one sign throughout
    morph = morph_targets(offsets)
    assert morph.names == ["offset_component_0_positive"] and morph.error_max < 1e-6
    assert not morph.targets[:, :25].any() and np.abs(morph.targets[:, 25:]).min(-1).all()
    assert morph_targets(np.zeros((3, 4, 3))).count == 0
    for bad in ({"tolerance": 0.0}, {"tolerance": float("nan")}, {"max_targets": 1}):
        with pytest.raises(ValueError, match="tolerance"):
            morph_targets(offsets, **bad)
    with pytest.raises(ValueError, match=r"\[T, V, 3\]"):
        morph_targets(offsets[0])


def test_axes_and_quaternions():
    np.testing.assert_allclose(up_to_y_rotation([0, 0, 1]), [[1, 0, 0], [0, 0, 1], [0, -1, 0]], atol=1e-12)
    np.testing.assert_allclose(up_to_y_rotation([0, -1, 0]) @ [0, -1, 0], [0, 1, 0], atol=1e-12)
    generators = torch.as_tensor(np.random.default_rng(2).normal(size=(64, 3, 3)))
    rotations = torch.linalg.matrix_exp(generators - generators.mT).numpy()  # exp of skew matrices
    quats = rotation_quaternions(rotations + 1e-7)
    np.testing.assert_allclose(np.stack([quaternion_matrix(q) for q in quats]), rotations, atol=1e-6)
    assert (quats[:, 3] >= 0).all()


def test_bad_input_is_refused(tmp_path, skinned_body, export_avatar, export_motion):
    animation = mesh_animation(export_avatar, skinned_body, export_motion)
    with pytest.raises(ValueError, match="needs a skinned mesh"):
        write_gltf(tmp_path / "x.glb", dataclasses.replace(skinned_body, joint_indices=None), animation)
    with pytest.raises(ValueError, match="strictly increasing"):
        write_gltf(tmp_path / "x.glb", skinned_body,
                   dataclasses.replace(animation, frame_ids=animation.frame_ids[::-1]))
    assert not (tmp_path / "x.glb").exists()
