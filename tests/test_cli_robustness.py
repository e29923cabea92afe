"""The commands run as subprocesses, as a user or a scheduler runs them: stop signals end a fit with a checkpoint
and a resume command, other commands without their temporary files; paths that are not UTF-8, impossible
devices, images whose header or codec misbehaves, a skeleton without size, an overflowing seed and
``warpavatar-fit-many``'s bad options and subject lists each end with exactly one line on stderr and exit
status 2 (no traceback, no crash, no C library's own lines); a huge skeleton is validated in linear time."""

import json
import os
import shlex
import shutil
import signal
import struct
import subprocess
import sys
import time
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from conftest import TINY_FIT
from test_bad_input import _log_steps
from warpavatar import data

DEMO = data.demo_subject_path()


NOT_UTF8 = os.fsdecode(b"caf\xe9")  # Latin-1 "cafe": a byte that is not UTF-8, kept by Python as a surrogate escape


def _environment():
    return dict(os.environ, PYTHONPATH=os.pathsep.join([str(Path(__file__).resolve().parents[1]),
                                                        os.environ.get("PYTHONPATH", "")]))


def _run(module, *arguments, cwd, timeout=300):
    """(exit status, stdout, stderr) of ``python -m warpavatar.cli.<module> arguments``."""
    done = subprocess.run([sys.executable, "-m", f"warpavatar.cli.{module}", *map(str, arguments)], cwd=cwd,
                          env=_environment(), capture_output=True, timeout=timeout)
    return (done.returncode, done.stdout.decode("utf-8", "backslashreplace"),
            done.stderr.decode("utf-8", "backslashreplace"))


def _start(module, *arguments, cwd):
    return subprocess.Popen([sys.executable, "-m", f"warpavatar.cli.{module}", *map(str, arguments)], cwd=cwd,
                            env=_environment(), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)


def assert_one_line(code, err, *named, status=2):
    """Exit status ``status`` and exactly one line on stderr, no traceback, naming each of ``named``."""
    lines = err.splitlines()
    assert code == status, (code, err)
    assert len(lines) == 1, err
    assert "Traceback" not in err
    for text in named:
        assert str(text) in lines[0], (text, lines[0])


@pytest.fixture
def folder(tmp_path):
    """A copy of the demo's training folder (50 frames of 128x128, 41 joints, masks)."""
    return Path(shutil.copytree(DEMO / "train", tmp_path / "train"))


def _wait_for(process, condition, *, timeout=180):
    deadline = time.time() + timeout
    while not condition():
        assert process.poll() is None, f"ended first: {process.stderr.read().decode()[-2000:]}"
        assert time.time() < deadline, "timed out"
        time.sleep(0.02)


# ----------------------------------------------------------------------------------------------------------
# Stop signals


@pytest.mark.parametrize("signal_number, status", [(signal.SIGTERM, 143), (signal.SIGHUP, 129)],
                         ids=["SIGTERM", "SIGHUP"])
def test_a_stop_signal_during_a_fit_writes_a_checkpoint_and_the_printed_command_resumes(folder, tmp_path,
                                                                                       signal_number, status):
    output = tmp_path / "out"
    process = _start("fit", folder, "-o", output, *TINY_FIT, "--iterations", "60", "--checkpoint-every", "1000",
                     cwd=tmp_path)
    _wait_for(process, lambda: _log_steps(output))  # training: its first step is logged
    process.send_signal(signal_number)
    err = process.communicate(timeout=120)[1].decode()
    name = signal.Signals(signal_number).name
    line = err.splitlines()[-1]  # (the lines before are the fit's warnings about its options, if any)
    assert process.returncode == status and "Traceback" not in err, err
    assert line.startswith(f"interrupted by {name} at step ") and " of 60: checkpoint written to " in line, err
    assert not (output / "avatar.pt").exists()
    stopped_at = int(torch.load(output / "checkpoint.pt", map_location="cpu", weights_only=False)["step"])
    assert 1 <= stopped_at < 60 and stopped_at == _log_steps(output)[-1]
    assert f"step {stopped_at} of 60" in line
    command = shlex.split(line.split("; resume with: ", 1)[1])
    assert command[0] == "warpavatar-fit" and "--resume" in command
    code, _, err = _run("fit", *command[1:], cwd=tmp_path)
    assert code == 0, err
    steps = _log_steps(output)
    assert steps[steps.index(stopped_at) + 1] == stopped_at + 1 and steps[-1] == 60
    assert (output / "avatar.pt").is_file()


def test_sigterm_to_fit_many_stops_its_fits_with_their_checkpoints_and_a_rerun_continues(tmp_path):
    pytest.importorskip("ray")
    (tmp_path / "alice").symlink_to(DEMO, target_is_directory=True)
    output = tmp_path / "out"
    arguments = [tmp_path / "alice", "-o", output, *TINY_FIT, "--iterations", "200", "--checkpoint-every", "1000"]
    process = _start("fit_many", *arguments, cwd=tmp_path)
    _wait_for(process, lambda: _log_steps(output / "alice"))  # its fit is training (on a Ray worker)
    process.send_signal(signal.SIGTERM)
    err = process.communicate(timeout=300)[1].decode()
    assert process.returncode == 143, err
    assert err.splitlines()[-1].startswith("interrupted by SIGTERM: the running fits stopped"), err  # (Ray's lines)
    assert not (output / "alice" / "avatar.pt").exists() and not (output / "alice" / "fit-many.json").exists()
    stopped_at = int(torch.load(output / "alice" / "checkpoint.pt", map_location="cpu", weights_only=False)["step"])
    assert 1 <= stopped_at < 200 and stopped_at == _log_steps(output / "alice")[-1]
    code, out, err = _run("fit_many", *arguments, cwd=tmp_path)
    assert code == 0, err
    assert f"alice: started on {os.uname().nodename}, resuming from step {stopped_at}" in out, out
    assert _log_steps(output / "alice")[-1] == 200 and (output / "alice" / "avatar.pt").is_file()


def test_sigterm_during_a_render_removes_its_temporary_frames(avatar_dir, tmp_path):
    with np.load(DEMO / "train" / "poses.npz") as archive:
        bones = archive["bone_transforms"]
    motion = tmp_path / "long.npz"
    np.savez(motion, bone_transforms=np.tile(bones, (100, 1, 1, 1)), fps=np.float32(30.0))  # 5000 frames
    output = tmp_path / "frames"
    process = _start("render", avatar_dir, "--motion", motion, "-o", output, "--size", "32", "--no-progress",
                     "--device", "cpu", cwd=tmp_path)

    def temporaries():  # the folder the frames go to until the last, named frames.tmp-<pid>-<random>
        return [path for path in tmp_path.glob("frames.tmp*") if path.is_dir()]

    _wait_for(process, lambda: any(any(folder.iterdir()) for folder in temporaries()))  # frames being written
    process.send_signal(signal.SIGTERM)
    err = process.communicate(timeout=120)[1].decode()
    assert_one_line(process.returncode, err, "interrupted by SIGTERM", status=143)
    assert not list(tmp_path.glob("frames*")), list(tmp_path.iterdir())


# ----------------------------------------------------------------------------------------------------------
# Paths that are not UTF-8 (OpenCV crashes on them)


def test_a_folder_whose_path_is_not_utf8_is_read(folder, tmp_path):
    # byte-safe reading: the folder loads, in a subprocess, as its UTF-8-named copy does (OpenCV given a path
    # with a surrogate escape crashes with a segmentation fault)
    odd = tmp_path / NOT_UTF8
    shutil.copytree(folder, odd)
    script = ("import sys, numpy; from warpavatar import data; "
              "videos = [data.load_video_folder(path, max_frames=5) for path in sys.argv[1:]]; "
              "print(numpy.array_equal(videos[0].images, videos[1].images), "
              "numpy.array_equal(videos[0].masks, videos[1].masks), videos[0].images.shape)")
    done = subprocess.run([sys.executable, "-c", script, str(odd), str(folder)], env=_environment(),
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.split() == ["True", "True", "(5,", "128,", "128,", "3)"]


def test_write_image_and_read_image_take_any_path(tmp_path):
    from warpavatar.io.images import read_image, write_image

    image = np.random.default_rng(0).integers(0, 256, (5, 7, 3), dtype=np.uint8)
    path = tmp_path / NOT_UTF8 / "a.png"
    path.parent.mkdir()
    write_image(path, image)
    assert np.array_equal(read_image(path), image)
    assert np.array_equal(cv2.imdecode(np.fromfile(path, np.uint8), cv2.IMREAD_COLOR)[..., ::-1], image)  # RGB


@pytest.mark.parametrize("where", ["input folder", "-o"])
def test_fit_refuses_a_path_that_is_not_utf8(folder, tmp_path, where):
    odd = tmp_path / NOT_UTF8
    if where == "input folder":
        shutil.copytree(folder, odd)
        arguments = [odd, "-o", tmp_path / "out"]
    else:
        arguments = [folder, "-o", odd]
    code, _, err = _run("fit", *arguments, *TINY_FIT, "--iterations", "2", cwd=tmp_path)
    assert_one_line(code, err, "caf\\xe9", "not valid UTF-8", "video_folder" if where == "input folder" else "-o")
    assert not (tmp_path / "out").exists() and not (where == "-o" and odd.exists())


def test_render_refuses_an_output_path_that_is_not_utf8(avatar_dir, tmp_path):
    code, _, err = _run("render", avatar_dir, "--motion", DEMO / "train", "-o", tmp_path / f"{NOT_UTF8}.mp4",
                        "--device", "cpu", cwd=tmp_path)
    assert_one_line(code, err, "-o", "caf\\xe9.mp4", "not valid UTF-8")


# ----------------------------------------------------------------------------------------------------------
# Devices


def test_fit_refuses_a_device_it_does_not_run_on(folder, tmp_path):
    code, _, err = _run("fit", folder, "-o", tmp_path / "out", "--device", "tpu", cwd=tmp_path)
    assert_one_line(code, err, "--device tpu", "cpu, cuda or cuda:N")


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")
def test_fit_refuses_cuda_where_there_is_none(folder, tmp_path):
    code, _, err = _run("fit", folder, "-o", tmp_path / "out", "--device", "cuda", cwd=tmp_path)
    assert_one_line(code, err, "--device cuda", "no CUDA device")


# ----------------------------------------------------------------------------------------------------------
# Images: a header that claims a huge size, a codec that warns on stderr


def _png_chunk(kind: bytes, payload: bytes) -> bytes:
    return struct.pack(">I", len(payload)) + kind + payload + struct.pack(">I", zlib.crc32(kind + payload))


def _png_with_bad_icc_profile(width: int, height: int) -> bytes:
    """A valid PNG whose iCCP chunk is too short to be a profile: libpng prints a warning on decoding it."""
    encoded = cv2.imencode(".png", np.zeros((height, width, 3), np.uint8))[1].tobytes()
    return encoded[:33] + _png_chunk(b"iCCP", b"bad\x00\x00" + zlib.compress(b"x" * 10)) + encoded[33:]  # after IHDR


def test_a_png_whose_header_claims_70000_pixels_a_side_is_one_line(folder, tmp_path):
    frame = sorted((folder / "frames").iterdir())[0]
    encoded = frame.read_bytes()
    header = _png_chunk(b"IHDR", struct.pack(">IIBBBBB", 70000, 70000, 8, 2, 0, 0, 0))
    frame.write_bytes(encoded[:8] + header + encoded[33:])
    code, _, err = _run("fit", folder, "-o", tmp_path / "out", *TINY_FIT, cwd=tmp_path)
    assert_one_line(code, err, frame.name, "70000x70000")


def test_a_codec_warning_does_not_reach_stderr(folder, tmp_path):
    # the PNG makes libpng warn: OpenCV's own decoding prints that line (checked first, so this test means
    # something), the fit's error about the same file is the only line
    probe = tmp_path / "probe.png"
    probe.write_bytes(_png_with_bad_icc_profile(64, 64))
    script = "import sys, cv2, numpy; cv2.imdecode(numpy.fromfile(sys.argv[1], numpy.uint8), cv2.IMREAD_UNCHANGED)"
    raw = subprocess.run([sys.executable, "-c", script, str(probe)], capture_output=True, text=True, timeout=60)
    assert "libpng warning" in raw.stderr, raw.stderr
    frame = sorted((folder / "frames").iterdir())[0]
    frame.write_bytes(probe.read_bytes())  # 64x64 where the camera says 128x128
    code, _, err = _run("fit", folder, "-o", tmp_path / "out", *TINY_FIT, cwd=tmp_path)
    assert_one_line(code, err, frame.name, "64x64", "128x128")


# ----------------------------------------------------------------------------------------------------------
# Numbers and skeletons


def test_a_skeleton_with_every_joint_at_one_point_is_one_line(folder, tmp_path):
    skeleton = json.loads((folder / "skeleton.json").read_text())
    for joint in skeleton["joints"]:
        joint["head"] = joint["tail"] = [0.5, 0.0, 1.0]
    (folder / "skeleton.json").write_text(json.dumps(skeleton))
    code, _, err = _run("fit", folder, "-o", tmp_path / "out", *TINY_FIT, cwd=tmp_path)
    assert_one_line(code, err, "skeleton.json", "one point [0.5, 0.0, 1.0]", "no size")


def test_a_seed_beyond_64_bits_is_one_line_naming_it(folder, tmp_path):
    code, _, err = _run("fit", folder, "-o", tmp_path / "out", "--seed", "99999999999999999999", cwd=tmp_path)
    assert_one_line(code, err, "--seed", "99999999999999999999", "64 bits")


def test_a_30000_joint_skeleton_is_validated_in_linear_time(tmp_path):
    # a tree of joints (each the child of joint (i - 1) // 2) took 10 s at 30000 joints with a quadratic
    # duplicate-name check. Not a speed benchmark: ten times the joints must cost well under a hundred times the
    # time (linear: about ten), timed back to back (the best of three each) so a busy machine slows both alike.
    from warpavatar.data.reader import read_skeleton

    rng = np.random.default_rng(0)

    def skeleton_file(count, name):
        joints = [{"name": f"joint{index}", "parent": (index - 1) // 2, "head": rng.random(3).tolist(),
                   "tail": rng.random(3).tolist()} for index in range(count)]
        path = tmp_path / name
        path.write_text(json.dumps({"format": data.SKELETON_FORMAT, "joints": joints}))
        return path, joints

    def best_time(path):
        times = []
        for _ in range(3):
            start = time.perf_counter()
            read_skeleton(path)
            times.append(time.perf_counter() - start)
        return min(times)

    small, _ = skeleton_file(3000, "small.json")
    large, joints = skeleton_file(30000, "large.json")
    assert best_time(large) < 30 * best_time(small)
    skeleton = read_skeleton(large)
    assert skeleton.joint_count == 30000 and skeleton.parents[29999] == 14999
    joints[29999]["name"] = "joint7"
    large.write_text(json.dumps({"format": data.SKELETON_FORMAT, "joints": joints}))
    with pytest.raises(data.VideoFolderError, match="joint names must be unique; repeated: joint7$"):
        read_skeleton(large)


def test_a_camera_of_width_0_names_the_file(tmp_path):
    from warpavatar.io.animation import read_cameras_json

    cameras = json.loads((DEMO / "train" / "cameras.json").read_text())
    cameras["width"] = 0
    path = tmp_path / "cameras.json"
    path.write_text(json.dumps(cameras))
    with pytest.raises(ValueError, match=r"cameras\.json: the camera's 'width' and 'height' must be 1 to 65536 "
                                         r"pixels, got 0x128$"):
        read_cameras_json(path, 3)


# ----------------------------------------------------------------------------------------------------------
# warpavatar-fit-many: its options and subject lists are checked before Ray starts


def test_fit_many_bad_option_is_one_line(tmp_path):
    code, _, err = _run("fit_many", DEMO, "-o", tmp_path / "out", "--no-such-option", cwd=tmp_path)
    assert_one_line(code, err, "warpavatar-fit-many: error: unrecognized arguments: --no-such-option")


@pytest.mark.parametrize("content, line, problem", [
    (b"\x7fELF\x02\x01\x01\x00\x00\x00\xff\xfe\n", 1, "is not UTF-8 text"),
    (json.dumps({"subjects": [str(DEMO)]}, indent=1).encode(), 1, "('{') names no folder"),
    (f"# the shoot\n{DEMO}\n\nnowhere\n".encode(), 4, "('nowhere') names no folder"),
], ids=["binary", "JSON", "a missing folder"])
def test_fit_many_refuses_a_subject_list_that_is_not_one(tmp_path, content, line, problem):
    listing = tmp_path / "subjects.txt"
    listing.write_bytes(content)
    code, _, err = _run("fit_many", listing, "-o", tmp_path / "out", cwd=tmp_path)
    assert_one_line(code, err, f"{listing}: line {line} {problem}")
    assert not (tmp_path / "out").exists()
