"""Fuzzing the video-folder reader: a few hundred random corruptions of a small valid folder (truncated and
garbled images, random bytes and changed values in the JSON files, arrays of other shapes and types in
poses.npz, missing, renamed and extra files). Every corruption must either still read or raise the project's own
VideoFolderError, with a one-line message that names a path inside the folder; nothing else may escape."""

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from warpavatar import data
from warpavatar.data import VideoFolderError

CASES = 400
SEED = 20261124

_JSON_VALUES = (None, True, -1, 0, 1, 2.5, -1e308, 1e308, float("nan"), float("inf"), "text", "", [], {}, [1, 2],
                [[1, 2, 3]] * 3, {"a": 1}, 2**70)


@pytest.fixture(scope="module")
def valid_folder(tmp_path_factory):
    """A valid folder of six demo frames (128x128, 41 joints, masks, a fixed camera) and its files' bytes."""
    video = data.load_video_folder(data.demo_subject_path() / "train", max_frames=6)
    folder = data.write_video_folder(video, tmp_path_factory.mktemp("fuzz") / "video")
    return folder


def _files(folder: Path) -> list[Path]:
    return sorted(path for path in folder.rglob("*") if path.is_file())


# ----------------------------------------------------------------------------------------------------------
# Corruptions: each takes (folder, rng) and changes the folder; it returns a description of what it did.


def _pick(rng, items):
    return items[int(rng.integers(len(items)))]


def _truncate(folder, rng):
    path = _pick(rng, _files(folder))
    raw = path.read_bytes()
    path.write_bytes(raw[:int(rng.integers(0, max(1, len(raw))))])
    return f"truncated {path.name}"


def _random_bytes(folder, rng):
    path = _pick(rng, _files(folder))
    raw = bytearray(path.read_bytes())
    for _ in range(int(rng.integers(1, 9))):
        if raw:
            raw[int(rng.integers(len(raw)))] = int(rng.integers(256))
    path.write_bytes(bytes(raw))
    return f"random bytes in {path.name}"


def _replace_with_noise(folder, rng):
    path = _pick(rng, _files(folder))
    path.write_bytes(rng.integers(0, 256, int(rng.integers(0, 2000)), dtype=np.uint8).tobytes())
    return f"{path.name} replaced by noise"


def _delete(folder, rng):
    path = _pick(rng, _files(folder))
    path.unlink()
    return f"deleted {path.name}"


def _json_nodes(value, path=()):
    yield path
    if isinstance(value, dict):
        for key, item in value.items():
            yield from _json_nodes(item, path + (key,))
    elif isinstance(value, list):
        for index, item in enumerate(value):
            yield from _json_nodes(item, path + (index,))


_DEEP = "@deep@"  # written as lists nested 5000 deep, deeper than a reader may recurse


def _json_value(rng):
    return _DEEP if rng.random() < 0.05 else _pick(rng, _JSON_VALUES)


def _edit_json_value(folder, rng):
    path = _pick(rng, [p for p in _files(folder) if p.suffix == ".json"])
    document = json.loads(path.read_text())
    nodes = list(_json_nodes(document))
    where = _pick(rng, nodes[1:]) if len(nodes) > 1 else ()
    if not where:
        document = _json_value(rng)
    else:
        parent = document
        for key in where[:-1]:
            parent = parent[key]
        action = rng.random()
        if action < 0.2:
            del parent[where[-1]]
        elif action < 0.3 and isinstance(parent, list):
            parent.append(parent[where[-1]])
        else:
            parent[where[-1]] = _json_value(rng)
    path.write_text(json.dumps(document).replace(json.dumps(_DEEP), "[" * 5000 + "]" * 5000))
    return f"{path.name} at {list(where)[:4]}"


def _npz_arrays(path):
    with np.load(path) as archive:
        return dict(archive)


def _edit_npz_array(folder, rng):
    path = folder / "poses.npz"
    arrays = _npz_arrays(path)
    key = _pick(rng, sorted(arrays))
    array = arrays[key]
    action = int(rng.integers(9))
    if action == 0:
        del arrays[key]
    elif action == 1 and array.ndim:
        axis = int(rng.integers(array.ndim))
        arrays[key] = np.take(array, np.arange(int(rng.integers(0, array.shape[axis] + 2)) % max(1, array.shape[axis])),
                              axis=axis)
    elif action == 2:
        arrays[key] = array.reshape(-1) if array.ndim != 1 else array[:, None]
    elif action == 3:
        arrays[key] = array.astype(_pick(rng, [np.int64, np.uint8, bool, np.complex64, np.float16, "U3"]))
    elif action == 4 and array.size:
        flat = np.real(array).astype(np.float64).reshape(-1)
        flat[int(rng.integers(flat.size))] = _pick(rng, [np.nan, np.inf, -np.inf, 1e30, -5.0])
        arrays[key] = flat.reshape(array.shape).astype(array.dtype if array.dtype.kind == "f" else np.float64)
    elif action == 5:
        arrays[key] = np.zeros((0,) + array.shape[1:], array.dtype)
    elif action == 6:
        arrays[key] = np.asarray(rng.normal(size=array.shape) * 10, dtype=array.dtype)
    elif action == 7 and array.ndim >= 2:
        arrays[key] = np.swapaxes(array, 0, 1)
    else:
        arrays["extra"] = rng.normal(size=(3,))
    np.savez(path, **arrays)
    return f"poses.npz {key!r} change {action}"


def _edit_image(folder, rng):
    path = _pick(rng, [p for p in _files(folder) if p.suffix == ".png"])
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise ValueError("an earlier corruption left no image to change")
    action = int(rng.integers(6))
    if action == 0:
        height, width = (int(value) for value in rng.integers(1, 200, 2))
        image = cv2.resize(image, (width, height), interpolation=cv2.INTER_NEAREST)
    elif action == 1:
        image = image.astype(np.uint16) * 257
    elif action == 2:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2BGRA) if image.ndim == 3 else np.dstack([image] * 4)
    elif action == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else np.dstack([image] * 3)
    elif action == 4:
        ok, encoded = cv2.imencode(".jpg", image if image.ndim == 2 else image[..., :3])
        path.write_bytes(encoded.tobytes())  # JPEG bytes under a .png name
        return f"{path.name} as JPEG bytes"
    else:
        image = rng.integers(0, 256, image.shape, dtype=np.uint8)
    cv2.imwrite(str(path), image)
    return f"{path.name} image change {action}"


def _rename_or_add(folder, rng):
    frames = sorted((folder / _pick(rng, ["frames", "masks"])).glob("*.png"))
    path = _pick(rng, frames)
    action = int(rng.integers(4))
    if action == 0:
        path.rename(path.with_name(_pick(rng, ["frame1.png", "1.png", "0000001.png", "000999.png", "000002.PNG"])))
    elif action == 1:
        shutil.copy(path, path.with_name(f"{int(rng.integers(0, 1000)):06d}.png"))
    elif action == 2:
        shutil.copy(path, path.with_suffix(".jpg"))  # a second file for the same frame id
    else:
        shutil.rmtree(path.parent)
    return f"{path.parent.name}/{path.name} file change {action}"


CORRUPTIONS = (_truncate, _random_bytes, _replace_with_noise, _delete, _edit_json_value, _edit_json_value,
               _edit_npz_array, _edit_npz_array, _edit_image, _rename_or_add)


def test_random_corruptions_read_or_raise_a_clear_error(valid_folder, tmp_path):
    rng = np.random.default_rng(SEED)
    originals = {path.relative_to(valid_folder): path.read_bytes() for path in _files(valid_folder)}
    folder = tmp_path / "video"
    failures, raised, still_read, skipped = [], 0, 0, 0
    for case in range(CASES):
        if folder.exists():
            shutil.rmtree(folder)
        for relative, raw in originals.items():
            (folder / relative).parent.mkdir(parents=True, exist_ok=True)
            (folder / relative).write_bytes(raw)
        corruptions = [_pick(rng, CORRUPTIONS) for _ in range(int(rng.integers(1, 3)))]
        done = []
        try:
            for corruption in corruptions:
                done.append(corruption(folder, rng))
        except Exception:  # noqa: BLE001 - zipfile, cv2 and json errors of a file already corrupted
            skipped += 1  # the second corruption found nothing it can change after the first
            continue
        try:
            data.load_video_folder(folder)
            still_read += 1
        except VideoFolderError as error:
            raised += 1
            message = str(error)
            if "\n" in message or not error.path.resolve().is_relative_to(folder.resolve()):
                failures.append(f"case {case} ({'; '.join(done)}): unclear message {message!r}")
        except Exception as error:  # noqa: BLE001 - anything else is what this test is looking for
            failures.append(f"case {case} ({'; '.join(done)}): {type(error).__name__}: {error}"[:400])
    assert not failures, f"{len(failures)} corruptions escaped as other errors:\n" + "\n".join(failures[:20])
    assert raised > CASES // 2 and still_read > 0 and skipped < CASES // 10, (raised, still_read, skipped)


# ----------------------------------------------------------------------------------------------------------
# The other files the avatar commands read: a render's --camera cameras.json and --motion sources (a poses .npz, a
# video folder's poses, a BVH). The same corruptions (and some of a BVH's text) must give either a successful
# load or a one-line ValueError whose message names the file; nothing else may escape.

SOURCE_CASES = 150

_BVH_WORDS = ("nan", "inf", "-inf", "1e300", "-1e300", "1e-300", "0", "-1", "3.5", "99999999999", "abc", "{", "}",
              "JOINT", "ROOT", "End", "Site", "OFFSET", "CHANNELS", "Xrotation", "Frames:", "Frame", "Time:", "MOTION")

_BVH_TEXT = """HIERARCHY
ROOT Hips
{
  OFFSET 0 10 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
  JOINT Abdomen
  {
    OFFSET 0 3 0
    CHANNELS 3 Zrotation Xrotation Yrotation
    End Site
    {
      OFFSET 0 4 0
    }
  }
  JOINT FootL
  {
    OFFSET 1 -9 0
    CHANNELS 3 Zrotation Xrotation Yrotation
    End Site
    {
      OFFSET 0 -1 1
    }
  }
}
MOTION
Frames: 3
Frame Time: 0.0333333
0 10 0 0 0 0 0 0 0 0 0 0
0 10.5 0 10 0 0 5 0 0 0 20 0
1 10 0 0 30 0 0 -5 0 10 0 0
"""


def _edit_bvh_text(folder, rng):
    path = folder / "motion.bvh"
    lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    row = int(rng.integers(len(lines))) if lines else 0
    action = int(rng.integers(4))
    if action == 0 and lines:
        words = lines[row].split() or [""]
        words[int(rng.integers(len(words)))] = _pick(rng, _BVH_WORDS)
        lines[row] = " ".join(words)
    elif action == 1 and lines:
        del lines[row]
    elif action == 2 and lines:
        lines.insert(row, lines[row])
    else:
        lines.insert(row, " ".join(_pick(rng, _BVH_WORDS) for _ in range(int(rng.integers(1, 6)))))
    path.write_text("\n".join(lines) + "\n")
    return f"motion.bvh line {row} change {action}"


def _with_fps(folder, rng):
    """A poses .npz with an 'fps' array (a motion file may carry one) of a random kind."""
    path = folder / "poses.npz"
    arrays = _npz_arrays(path)
    arrays["fps"] = np.asarray(_pick(rng, [30.0, 0.0, -1.0, 1e300, np.nan, 1000.0, 1001.0, 24, "30", [30.0, 25.0]]))
    np.savez(path, **arrays)
    return f"poses.npz fps {arrays['fps']!r}"


_FILE_CORRUPTIONS = (_truncate, _random_bytes, _replace_with_noise)


def _source_cases(original: Path, corruptions, read, tmp_path, seed):
    """Corrupt copies of the folder ``original`` ``SOURCE_CASES`` times; ``read(folder)`` each. Returns the
    failures, and how many cases read and how many raised."""
    rng = np.random.default_rng(seed)
    originals = {path.relative_to(original): path.read_bytes() for path in _files(original)}
    folder = tmp_path / original.name
    failures, raised, still_read = [], 0, 0
    for case in range(SOURCE_CASES):
        if folder.exists():
            shutil.rmtree(folder)
        for relative, raw in originals.items():
            (folder / relative).parent.mkdir(parents=True, exist_ok=True)
            (folder / relative).write_bytes(raw)
        done = []
        try:
            for corruption in [_pick(rng, corruptions) for _ in range(int(rng.integers(1, 3)))]:
                done.append(corruption(folder, rng))
        except Exception:  # noqa: BLE001 - the second corruption found nothing it can change after the first
            continue
        try:
            read(folder)
            still_read += 1
        except ValueError as error:
            raised += 1
            message = str(error)
            if "\n" in message or str(folder) not in message:
                failures.append(f"case {case} ({'; '.join(done)}): unclear message {message!r}")
        except Exception as error:  # noqa: BLE001 - anything else is what this test is looking for
            failures.append(f"case {case} ({'; '.join(done)}): {type(error).__name__}: {error}"[:400])
    return failures, raised, still_read


@pytest.fixture(scope="module")
def skeleton(valid_folder):
    return data.load_video_folder(valid_folder, max_frames=1).skeleton


@pytest.mark.parametrize("per_frame", [False, True], ids=["fixed", "per-frame"])
def test_corrupt_render_cameras_read_or_raise_a_clear_error(valid_folder, tmp_path, per_frame):
    from warpavatar.io.animation import read_cameras_json

    original = tmp_path / "render_camera"
    original.mkdir()
    document = json.loads((valid_folder / "cameras.json").read_text())
    if per_frame:
        document["frames"] = [{"K": document["K"], "world_to_camera": document["world_to_camera"]}] * 3
    (original / "cameras.json").write_text(json.dumps(document))
    read_cameras_json(original / "cameras.json", 3)  # the uncorrupted file reads
    failures, raised, still_read = _source_cases(
        original, _FILE_CORRUPTIONS + (_edit_json_value,) * 3,
        lambda folder: read_cameras_json(folder / "cameras.json", 3), tmp_path / "cases", SEED + per_frame)
    assert not failures, f"{len(failures)} corruptions escaped:\n" + "\n".join(failures[:20])
    assert raised > SOURCE_CASES // 3 and still_read > 0, (raised, still_read)


@pytest.mark.parametrize("source", ["npz", "folder"])
def test_corrupt_motion_files_load_or_raise_a_clear_error(valid_folder, skeleton, tmp_path, source):
    from warpavatar.io.motion import load_motion

    original = tmp_path / "motion"
    original.mkdir()
    names = ("poses.npz",) if source == "npz" else ("poses.npz", "meta.json", "skeleton.json")
    for name in names:
        shutil.copy(valid_folder / name, original / name)
    target = (lambda folder: folder / "poses.npz") if source == "npz" else (lambda folder: folder)
    load_motion(target(original), skeleton)
    corruptions = _FILE_CORRUPTIONS + (_edit_npz_array,) * 3 + (_with_fps,)
    if source == "folder":
        corruptions += (_edit_json_value,) * 2
    failures, raised, still_read = _source_cases(original, corruptions,
                                                 lambda folder: load_motion(target(folder), skeleton),
                                                 tmp_path / "cases", SEED + len(names))
    assert not failures, f"{len(failures)} corruptions escaped:\n" + "\n".join(failures[:20])
    assert raised > SOURCE_CASES // 3 and still_read > 0, (raised, still_read)


def test_corrupt_bvh_files_load_or_raise_a_clear_error(skeleton, tmp_path):
    from warpavatar.io.motion import load_motion

    original = tmp_path / "bvh"
    original.mkdir()
    (original / "motion.bvh").write_text(_BVH_TEXT)
    assert load_motion(original / "motion.bvh", skeleton).frame_count == 3
    failures, raised, still_read = _source_cases(
        original, _FILE_CORRUPTIONS + (_edit_bvh_text,) * 6,
        lambda folder: load_motion(folder / "motion.bvh", skeleton), tmp_path / "cases", SEED + 7)
    assert not failures, f"{len(failures)} corruptions escaped:\n" + "\n".join(failures[:20])
    assert raised > SOURCE_CASES // 3 and still_read > 0, (raised, still_read)
