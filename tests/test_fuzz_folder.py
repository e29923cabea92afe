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
