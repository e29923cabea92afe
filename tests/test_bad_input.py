"""Bad input to the commands, one case per class: each is built from a small valid folder, runs the command's
``main`` in-process and must end with exit status 2, a single line on stderr that names the file or option, no
traceback and nothing at the output's final name. Then what bad input is accepted (JPG, RGBA, grey and 16-bit
frames), and interruptions: Ctrl-C during a fit, kill -9 during a fit and during a USD export."""

import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from conftest import TINY_FIT
from warpavatar import data
from warpavatar.cli import fit

DEMO = data.demo_subject_path()



def run_command(main, argv, capsys):
    """(exit status, stdout, stderr) of ``main(argv)``; argparse's own exits count as a status."""
    try:
        code = main([str(argument) for argument in argv])
    except SystemExit as stop:
        code = stop.code
    out, err = capsys.readouterr()
    return code, out, err


def assert_bad_input(code, err, *named):
    """Exit status 2 and one line on stderr, no traceback, naming each of ``named``."""
    lines = err.strip().splitlines()
    assert code == 2, (code, err)
    assert len(lines) == 1, err
    assert "Traceback" not in err
    for text in named:
        assert str(text).lower() in lines[0].lower(), (text, lines[0])


@pytest.fixture
def folder(tmp_path):
    """A copy of the demo's training folder (50 frames of 128x128, 41 joints, masks)."""
    return Path(shutil.copytree(DEMO / "train", tmp_path / "train"))


def _edit_json(path, edit):
    value = json.loads(path.read_text())
    edit(value)
    path.write_text(json.dumps(value))


def _frame(folder, index):
    return sorted((folder / "frames").iterdir())[index]


# ----------------------------------------------------------------------------------------------------------
# warpavatar-fit: the video folder. Each case edits a valid folder and returns (the folder to fit, what the
# message must name).


def _nonexistent(folder):
    return folder.parent / "nowhere", ("nowhere", "no such")


def _empty(folder):
    shutil.rmtree(folder)
    folder.mkdir()
    return folder, (folder.name, "empty")


def _video_file_as_folder(folder):
    clip = folder.parent / "clip.mp4"
    writer = cv2.VideoWriter(str(clip), cv2.VideoWriter_fourcc(*"mp4v"), 30, (32, 32))
    for value in (40, 200):
        writer.write(np.full((32, 32, 3), value, np.uint8))
    writer.release()
    return clip, ("clip.mp4", "video file")


def _video_in_frames(folder):
    shutil.rmtree(folder / "frames")
    (folder / "frames").mkdir()
    shutil.copy(_video_file_as_folder(folder)[0], folder / "frames" / "clip.mp4")
    return folder, ("frames", "clip.mp4")


def _frames_of_different_sizes(folder):
    odd = _frame(folder, 7)
    cv2.imwrite(str(odd), cv2.resize(cv2.imread(str(odd)), (96, 128)))
    return folder, (odd.name, "96x128", "size mismatch")


def _rgba_and_rgb_frames_without_masks(folder):
    shutil.rmtree(folder / "masks")
    odd = _frame(folder, 3)
    image = cv2.imread(str(odd))
    cv2.imwrite(str(odd), np.dstack([image, np.full(image.shape[:2], 255, np.uint8)]))
    return folder, (odd.name, "alpha")


def _per_frame_cameras_of_wrong_count(folder):
    def edit(cameras):
        one = {"K": cameras["K"], "world_to_camera": cameras["world_to_camera"]}
        cameras["frames"] = [one] * 7
    _edit_json(folder / "cameras.json", edit)
    return folder, ("cameras.json", "7 entries", "50 frames")


def _duplicate_joint_names(folder):
    def edit(skeleton):
        skeleton["joints"][5]["name"] = skeleton["joints"][2]["name"]
    _edit_json(folder / "skeleton.json", edit)
    name = json.loads((DEMO / "train" / "skeleton.json").read_text())["joints"][2]["name"]
    return folder, ("skeleton.json", "unique", name)


def _skeleton_too_deep(folder):
    def edit(skeleton):
        joint = skeleton["joints"][0]
        skeleton["joints"] = [dict(joint, name=f"link{index}", parent=index - 1) for index in range(200)]
    _edit_json(folder / "skeleton.json", edit)
    return folder, ("skeleton.json", "link128", "deep")


def _truncated_frame(folder):
    frame = _frame(folder, 11)
    frame.write_bytes(frame.read_bytes()[:200])
    return folder, (frame.name, "cannot be read")


def _poses_of_another_joint_count(folder):
    with np.load(folder / "poses.npz") as archive:
        arrays = dict(archive)
    arrays["bone_transforms"] = arrays["bone_transforms"][:, :40]
    arrays.pop("joint_positions", None)
    np.savez(folder / "poses.npz", **arrays)
    return folder, ("poses.npz", "joint count mismatch")


@pytest.mark.parametrize("case", [_nonexistent, _empty, _video_file_as_folder, _video_in_frames,
                                  _frames_of_different_sizes, _rgba_and_rgb_frames_without_masks,
                                  _per_frame_cameras_of_wrong_count, _duplicate_joint_names, _skeleton_too_deep,
                                  _truncated_frame, _poses_of_another_joint_count],
                         ids=lambda case: case.__name__.strip("_"))
def test_fit_bad_folder(folder, tmp_path, capsys, case):
    path, named = case(folder)
    output = tmp_path / "out"
    code, _, err = run_command(fit.main, [path, "-o", output, *TINY_FIT], capsys)
    assert_bad_input(code, err, *named)
    assert not output.exists()


# ----------------------------------------------------------------------------------------------------------
# warpavatar-fit: options and the output folder


@pytest.mark.parametrize("options, named", [
    (["--iterations", "-5"], ["--iterations", "-5"]),
    (["--iterations", "0"], ["--iterations", "at least 1"]),
    (["--iterations", "1000000000"], ["--iterations", "at most"]),
    (["--iterations", "many"], ["--iterations", "many"]),
    (["--image-scale", "0"], ["--image-scale", "above 0"]),
    (["--image-scale", "-0.5"], ["--image-scale"]),
    (["--image-scale", "50"], ["--image-scale", "at most 4"]),
    (["--image-scale", "nan"], ["--image-scale", "nan"]),
    (["--grid-cells", "0"], ["--grid-cells"]),
    (["--grid-cells", "100000"], ["--grid-cells", "at most 512"]),
    (["--grid-cells", "8", "--grid-min-cells", "16"], ["--grid-min-cells", "--grid-cells"]),
    (["--checkpoint-every", "0"], ["--checkpoint-every"]),
    (["--sh-degree", "7"], ["--sh-degree"]),
    (["--lr-color", "inf"], ["--lr-color"]),
], ids=lambda value: " ".join(value) if isinstance(value, list) and value[0].startswith("--") else "")
def test_fit_bad_option(folder, tmp_path, capsys, options, named):
    output = tmp_path / "out"
    code, _, err = run_command(fit.main, [folder, "-o", output, *TINY_FIT, *options], capsys)
    assert_bad_input(code, err, *named)
    assert not output.exists()


def test_fit_output_is_a_file(folder, tmp_path, capsys):
    output = tmp_path / "notes.txt"
    output.write_text("mine")
    code, _, err = run_command(fit.main, [folder, "-o", output, *TINY_FIT], capsys)
    assert_bad_input(code, err, "notes.txt", "is a file")
    assert output.read_text() == "mine"


def test_fit_output_below_a_file(folder, tmp_path, capsys):
    (tmp_path / "notes.txt").write_text("mine")
    code, _, err = run_command(fit.main, [folder, "-o", tmp_path / "notes.txt" / "out", *TINY_FIT], capsys)
    assert_bad_input(code, err, "notes.txt", "below")


def test_fit_refuses_a_non_empty_output_folder(folder, tmp_path, capsys):
    output = tmp_path / "out"
    output.mkdir()
    (output / "holiday.jpg").write_bytes(b"not mine to delete")
    code, _, err = run_command(fit.main, [folder, "-o", output, *TINY_FIT], capsys)
    assert_bad_input(code, err, "-o", "not empty", "holiday.jpg", "--resume", "--overwrite")
    assert sorted(path.name for path in output.iterdir()) == ["holiday.jpg"]
    code, _, err = run_command(fit.main, [folder, "-o", output, "--resume", "--overwrite", *TINY_FIT], capsys)
    assert_bad_input(code, err, "--resume", "--overwrite")


def test_fit_overwrite_deletes_only_an_earlier_fits_outputs(tmp_path):
    output = tmp_path / "out"
    (output / "previews").mkdir(parents=True)
    for name in ("avatar.pt", "checkpoint.pt", "checkpoint.pt.tmp-41-0123456789ab", "train_log.jsonl",
                 "previews/000001.png", "holiday.jpg", "checkpoint.pt.tmp"):
        (output / name).write_bytes(b"old")
    fit.remove_fit_outputs(output)
    # the temporary file an interrupted fit left goes; a file that merely looks like an old temporary name stays
    assert sorted(path.name for path in output.iterdir()) == ["checkpoint.pt.tmp", "holiday.jpg"]
    fit.check_output_folder(output, resume=False, overwrite=True)  # allowed with --overwrite


# ----------------------------------------------------------------------------------------------------------
# warpavatar-animate: motions and the output file


def _animate(avatar_dir, motion, output, capsys, *options):
    from warpavatar.cli import animate

    pytest.importorskip("pxr")
    return run_command(animate.main, [avatar_dir, "--motion", motion, "-o", output, "--no-progress", "--device",
                                      "cpu", *options], capsys)


def _bvh(path, root, child, *, depth=1):
    """A BVH of a root and a chain of ``depth`` joints named ``child``, ``child``1, ...; three frames."""
    lines = [f"HIERARCHY", f"ROOT {root}", "{", " OFFSET 0 0 0",
             " CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation"]
    for level in range(depth):
        lines += [f"JOINT {child}{level or ''}", "{", " OFFSET 0 10 0", " CHANNELS 3 Zrotation Xrotation Yrotation"]
    lines += ["End Site", "{", " OFFSET 0 10 0", "}"] + ["}"] * (depth + 1)
    values = 6 + 3 * depth
    lines += ["MOTION", "Frames: 3", "Frame Time: 0.0333333"] + [" ".join(["0"] * values)] * 3
    path.write_text("\n".join(lines) + "\n")
    return path


def test_animate_motion_of_another_skeleton(avatar_dir, tmp_path, capsys):
    motion = Path(shutil.copytree(DEMO / "novel_pose" / "dance_cam000", tmp_path / "dance"))
    names = [joint["name"] for joint in json.loads((motion / "skeleton.json").read_text())["joints"]]
    _edit_json(motion / "skeleton.json", lambda skeleton: skeleton["joints"][4].update(name="tail_tip"))
    output = tmp_path / "a.usdc"
    code, _, err = _animate(avatar_dir, motion, output, capsys)
    assert_bad_input(code, err, "skeleton.json", "another skeleton", "tail_tip", names[4])
    assert not output.exists() and not list(tmp_path.glob("*.tmp*"))


def test_animate_bvh_with_unknown_joint_names(avatar_dir, tmp_path, capsys):
    bvh = _bvh(tmp_path / "walk.bvh", "Wurzel", "Schwanz")
    output = tmp_path / "a.usdc"
    code, _, err = _animate(avatar_dir, bvh, output, capsys)
    assert_bad_input(code, err, "walk.bvh", "no joint of the skeleton maps", "Wurzel", "Schwanz", "name_map")
    assert not output.exists()


def test_animate_bvh_partly_matched_says_which_joints_it_does_not_drive(avatar_dir, tmp_path, capsys):
    skeleton = data.load_video_folder(DEMO / "train", max_frames=1).skeleton
    child = skeleton.names[int(np.nonzero(skeleton.parents == 0)[0][0])]
    bvh = _bvh(tmp_path / "walk.bvh", skeleton.names[0], child)
    code, out, _ = _animate(avatar_dir, bvh, tmp_path / "a.usdc", capsys)
    assert code == 0
    note = next(line for line in out.splitlines() if line.startswith("note:"))
    undriven = [name for name in skeleton.names if name not in (skeleton.names[0], child)]
    assert f"{len(undriven)} avatar joints" in note and undriven[0] in note and "walk.bvh" in note


def test_animate_bvh_nested_too_deep(avatar_dir, tmp_path, capsys):
    bvh = _bvh(tmp_path / "deep.bvh", "Hips", "Spine", depth=400)
    code, _, err = _animate(avatar_dir, bvh, tmp_path / "a.usdc", capsys)
    assert_bad_input(code, err, "deep.bvh", "line", "128 deep")


def test_animate_name_map_that_is_not_json(avatar_dir, tmp_path, capsys):
    bvh = _bvh(tmp_path / "walk.bvh", "Hips", "Spine")
    (tmp_path / "map.json").write_text("{'hips': 'Hips'")
    code, _, err = _animate(avatar_dir, bvh, tmp_path / "a.usdc", capsys, "--name-map", tmp_path / "map.json")
    assert_bad_input(code, err, "--name-map", "map.json", "JSON")


def test_animate_output_below_a_file(avatar_dir, tmp_path, capsys):
    (tmp_path / "notes.txt").write_text("mine")
    code, _, err = _animate(avatar_dir, DEMO / "novel_pose" / "dance_cam000", tmp_path / "notes.txt" / "a.usdc",
                            capsys, "--frames", "0:2")
    assert_bad_input(code, err, "notes.txt")


@pytest.mark.parametrize("command, options, named", [
    ("animate", ["-o", "{out}/a.usdc", "--fps", "0"], ["--fps", "'0'"]),
    ("animate", ["-o", "{out}/a.usdc", "--bvh-scale", "-1"], ["--bvh-scale", "-1"]),
    ("animate", ["-o", "{out}"], ["-o", "is a folder"]),
    ("animate", ["-o", "{out}/a.usdc", "--frames", "5:2"], ["poses.npz", "no frames"]),
    ("render", ["-o", "{out}/r.mp4", "--size", "0"], ["--size", "0"]),
    ("render", ["-o", "{out}/r.mp4", "--background", "2", "0", "0"], ["--background", "0..1"]),
    ("render", ["-o", "{out}/notes.txt/frames"], ["-o", "notes.txt", "below"]),
    ("eval", ["--json", "{out}/notes.txt/result.json"], ["--json", "notes.txt", "below"]),
    ("eval", ["--save-renders", "{out}/notes.txt"], ["--save-renders", "notes.txt", "is a file"]),
], ids=lambda value: "-".join(value) if isinstance(value, list) else value)
def test_avatar_command_bad_option(avatar_dir, tmp_path, capsys, command, options, named):
    from warpavatar.cli import animate, eval as evaluate, render

    (tmp_path / "notes.txt").write_text("mine")
    motion = DEMO / "novel_pose" / "dance_cam000"
    options = [option.format(out=tmp_path) for option in options]
    main = {"animate": animate.main, "render": render.main, "eval": evaluate.main}[command]
    argv = [avatar_dir, motion] if command == "eval" else [avatar_dir, "--motion", motion]
    code, _, err = run_command(main, [*argv, *options, "--no-progress", "--device", "cpu"], capsys)
    assert_bad_input(code, err, *named)
    assert sorted(path.name for path in tmp_path.iterdir()) == ["notes.txt"]


# ----------------------------------------------------------------------------------------------------------
# Frames that are accepted: JPG, RGBA (alpha composited over the background and used as the mask), grey, 16-bit


def test_jpg_frames_are_read(folder):
    reference = data.load_video_folder(folder)
    for path in sorted((folder / "frames").iterdir()):
        cv2.imwrite(str(path.with_suffix(".jpg")), cv2.imread(str(path)), [cv2.IMWRITE_JPEG_QUALITY, 95])
        path.unlink()
    video = data.load_video_folder(folder)
    difference = np.abs(video.images.astype(int) - reference.images.astype(int))
    assert 0 < difference.mean() < 2.0  # JPEG's loss, nothing more
    np.testing.assert_array_equal(video.masks, reference.masks)


def test_rgba_frames_give_the_masks_and_are_composited_over_the_background(folder):
    reference = data.load_video_folder(folder)
    masks = sorted((folder / "masks").iterdir())
    rng = np.random.default_rng(0)
    for path, mask_path in zip(sorted((folder / "frames").iterdir()), masks):
        image = cv2.imread(str(path))
        image[cv2.imread(str(mask_path), cv2.IMREAD_GRAYSCALE) == 0] = rng.integers(0, 255, 3)  # noise behind
        alpha = cv2.imread(str(mask_path), cv2.IMREAD_GRAYSCALE)
        cv2.imwrite(str(path), np.dstack([image, alpha]))
    shutil.rmtree(folder / "masks")
    _edit_json(folder / "meta.json", lambda meta: meta.update(background=[0.0, 1.0, 0.0]))
    video = data.load_video_folder(folder, scale=0.5)
    expected = data.load_video_folder(DEMO / "train", scale=0.5)
    np.testing.assert_array_equal(video.masks, expected.masks)
    outside = video.masks == 0
    assert outside.any()
    # full-scale pixels outside the subject are the background exactly; inside they are the frame's own
    full = data.load_video_folder(folder)
    behind = reference.masks == 0
    assert np.all(full.images[behind] == [0, 255, 0])
    np.testing.assert_array_equal(full.images[~behind], reference.images[~behind])


def test_grey_and_16_bit_frames_are_read(folder):
    reference = data.load_video_folder(folder, max_frames=2)
    first, second = _frame(folder, 0), _frame(folder, 1)
    cv2.imwrite(str(first), cv2.cvtColor(cv2.imread(str(first)), cv2.COLOR_BGR2GRAY))
    cv2.imwrite(str(second), cv2.imread(str(second)).astype(np.uint16) * 257)
    video = data.load_video_folder(folder, max_frames=2)
    expected_grey = cv2.cvtColor(reference.images[0], cv2.COLOR_RGB2GRAY)
    np.testing.assert_array_equal(video.images[0], np.repeat(expected_grey[..., None], 3, axis=2))
    np.testing.assert_array_equal(video.images[1], reference.images[1])


# ----------------------------------------------------------------------------------------------------------
# Interruptions


def _log_steps(output):
    path = output / "train_log.jsonl"
    if not path.is_file():
        return []
    return [record["step"] for line in path.read_text().splitlines() if line.endswith("}")
            for record in [json.loads(line)] if "step" in record]


def _checkpoint_step(output):
    return int(torch.load(output / "checkpoint.pt", map_location="cpu", weights_only=True)["step"])


def test_ctrl_c_during_a_fit_writes_a_checkpoint_and_says_how_to_resume(folder, tmp_path, capsys):
    output = tmp_path / "out"
    argv = [str(folder), "-o", str(output), *TINY_FIT, "--iterations", "40", "--checkpoint-every", "1000"]

    def interrupt_at_step_3():
        deadline = time.time() + 120
        while time.time() < deadline and not any(step >= 3 for step in _log_steps(output)):
            time.sleep(0.01)
        os.kill(os.getpid(), signal.SIGINT)

    thread = threading.Thread(target=interrupt_at_step_3)
    thread.start()
    code, _, err = run_command(fit.main, argv, capsys)
    thread.join()
    assert code == 130, err
    assert not (output / "avatar.pt").exists()
    stopped_at = _checkpoint_step(output)
    assert 3 <= stopped_at < 40 and stopped_at == _log_steps(output)[-1]
    line = err.strip().splitlines()[-1]
    assert f"step {stopped_at} of 40" in line and "resume with: warpavatar-fit" in line and "--resume" in line
    # the printed command continues where it stopped, in this folder, to the end
    resume = line.split("resume with: warpavatar-fit ", 1)[1]
    import shlex
    code, _, err = run_command(fit.main, shlex.split(resume), capsys)
    assert code == 0, err
    steps = _log_steps(output)
    assert steps[steps.index(stopped_at) + 1] == stopped_at + 1 and steps[-1] == 40
    assert (output / "avatar.pt").is_file()


def test_resume_with_other_options_lists_the_differences(folder, tmp_path, capsys):
    output = tmp_path / "out"
    argv = [folder, "-o", output, *TINY_FIT, "--iterations", "3"]
    code, _, err = run_command(fit.main, argv, capsys)
    assert code == 0, err
    code, _, err = run_command(fit.main, [*argv, "--resume", "--iterations", "6", "--lambda-mask", "0.3"], capsys)
    assert_bad_input(code, err, "checkpoint.pt", "--iterations: 3 in the checkpoint vs 6 given",
                     "--lambda-mask: 0.1 in the checkpoint vs 0.3 given")
    assert "--seed" not in err


def test_resume_from_a_corrupt_checkpoint(folder, tmp_path, capsys):
    output = tmp_path / "out"
    output.mkdir()
    (output / "checkpoint.pt").write_bytes(b"PK\x03\x04 not really a checkpoint")
    code, _, err = run_command(fit.main, [folder, "-o", output, *TINY_FIT, "--iterations", "3", "--resume"], capsys)
    assert_bad_input(code, err, "checkpoint.pt", "cannot read the checkpoint")
    assert not (output / "avatar.pt").exists()


def _start(arguments, cwd):
    environment = dict(os.environ, PYTHONPATH=os.pathsep.join(
        [str(Path(__file__).resolve().parents[1]), os.environ.get("PYTHONPATH", "")]))
    return subprocess.Popen([sys.executable, *arguments], cwd=cwd, env=environment, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE)


def _kill_when(process, condition, *, timeout=120):
    """SIGKILL ``process`` as soon as ``condition()`` holds; fails if it ended first."""
    deadline = time.time() + timeout
    while not condition():
        assert process.poll() is None, f"ended before it could be killed: {process.stderr.read().decode()[-2000:]}"
        assert time.time() < deadline, "timed out"
        time.sleep(0.005)
    assert process.poll() is None, "ended before it could be killed"
    process.kill()
    process.wait()
    process.stderr.close()


def test_kill_9_during_a_fit_leaves_no_avatar_and_resume_loses_at_most_one_interval(folder, tmp_path, capsys):
    output = tmp_path / "out"
    every = 5
    argv = [str(folder), "-o", str(output), *TINY_FIT, "--iterations", "60", "--checkpoint-every", str(every)]
    process = _start(["-m", "warpavatar.cli.fit", *argv], tmp_path)
    _kill_when(process, lambda: (output / "checkpoint.pt").is_file())
    reached = _log_steps(output)[-1]
    saved = _checkpoint_step(output)
    assert not (output / "avatar.pt").exists() and not (output / "canonical.ply").exists()
    assert saved % every == 0 and 0 <= reached - saved <= every, (saved, reached)
    logged = len(_log_steps(output))
    code, _, err = run_command(fit.main, [*argv, "--resume"], capsys)
    assert code == 0, err
    resumed = _log_steps(output)[logged:]
    assert resumed[0] == saved + 1 and resumed[-1] == 60
    assert (output / "avatar.pt").is_file()


def test_kill_9_during_a_usd_export_leaves_no_file_at_the_final_name(avatar_dir, tmp_path):
    pytest.importorskip("pxr")
    with np.load(DEMO / "train" / "poses.npz") as archive:
        bones = archive["bone_transforms"]
    motion = tmp_path / "long.npz"
    np.savez(motion, bone_transforms=np.tile(bones, (200, 1, 1, 1)), fps=np.float32(30.0))  # 10000 frames
    output = tmp_path / "long.usdc"
    process = _start(["-m", "warpavatar.cli.animate", str(avatar_dir), "--motion", str(motion), "-o", str(output),
                      "--device", "cpu"], tmp_path)
    def exporting():  # the temporary file exists and frames are being written
        found = list(tmp_path.glob("long.tmp-*.usdc"))
        return len(found) == 1 and found[0].stat().st_size > 0 and time.sleep(0.5) is None

    _kill_when(process, exporting)
    assert not output.exists()
    # the next export of that name goes through, removing the temporary file the killed one left
    from warpavatar.cli import animate
    assert animate.main([str(avatar_dir), "--motion", str(DEMO / "train"), "-o", str(output), "--frames", "0:3",
                         "--no-progress", "--device", "cpu"]) == 0
    assert output.is_file() and not list(tmp_path.glob("long.tmp*"))
