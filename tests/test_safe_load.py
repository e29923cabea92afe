"""Nothing runs from a loaded file, and ``--resume`` refuses what it cannot continue.

Every command that reads an avatar file or a checkpoint is given a crafted pickle whose unpickling would create a
marker file: each must end with exit status 2 and one line on stderr naming the file, and the marker must not
exist. Real files still load; a resume on another video folder, with another skeleton, or of a finished fit with
other options is refused with one line naming the checkpoint and what differs."""

import json
import pathlib
import pickle
import shutil
import subprocess
import sys

import numpy as np
import pytest
import torch

from conftest import TINY_FIT
from test_bad_input import assert_bad_input, run_command
from warpavatar import data
from warpavatar.batch.job import fit_subject
from warpavatar.batch.subjects import BatchSubject
from warpavatar.cli import eval as eval_cli
from warpavatar.cli import fit
from warpavatar.fit import preset
from warpavatar.fit.checkpoint import CHECKPOINT_FORMAT, read_checkpoint
from warpavatar.model import AVATAR_FORMAT, Avatar

DEMO = data.demo_subject_path()
# TINY_FIT finished: every stage it has starts before the end, so nothing is printed on stderr
FIT = [*TINY_FIT, "--iterations", "21", "--refine-poses", "off", "--sh-increase-every", "10"]


class TouchOnLoad:
    """Pickles as a call of ``Path.touch(marker)``: unpickling it creates the marker."""

    def __init__(self, marker):
        self.marker = pathlib.Path(marker)

    def __reduce__(self):
        return pathlib.Path.touch, (self.marker,)


def _craft(path, marker, *, tag: str, layout: str = "torch") -> pathlib.Path:
    """Write a file at ``path`` that looks like a warpavatar file of format ``tag`` and creates ``marker`` when
    fully unpickled: through ``torch.save`` (``layout="torch"``) or a bare pickle of protocol 2 or 4."""
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {"format": tag, "step": 1, "skeleton": TouchOnLoad(marker)}
    if layout == "torch":
        torch.save(state, path)
    else:
        path.write_bytes(pickle.dumps(state, protocol=int(layout.removeprefix("pickle"))))
    return path


def _run(module, arguments, cwd):
    """(exit status, stderr) of the command ``warpavatar.cli.<module>`` run as its console script runs it (its
    ``main`` in a process of its own)."""
    script = f"import sys; from warpavatar.cli.{module} import main; sys.exit(main(sys.argv[1:]))"
    done = subprocess.run([sys.executable, "-c", script, *map(str, arguments)], cwd=cwd, capture_output=True,
                          text=True, timeout=300)
    return done.returncode, done.stderr


def _assert_refused_unpickling(code, err, path):
    lines = err.strip().splitlines()
    assert code == 2, (code, err)
    assert len(lines) == 1, err
    assert lines[0].startswith(f"error: {path}: the "), lines[0]
    assert "holds objects other than tensors and plain containers" in lines[0], lines[0]
    assert lines[0].endswith("and was not loaded (nothing in it ran)"), lines[0]


def test_the_crafted_payload_runs_when_fully_unpickled(tmp_path):
    """The files below are live: a full unpickler creates the marker (so the tests that it stays absent can
    fail)."""
    for layout in ("torch", "pickle2", "pickle4"):
        marker = tmp_path / f"ran-{layout}"
        path = _craft(tmp_path / f"{layout}.pt", marker, tag=AVATAR_FORMAT, layout=layout)
        if layout == "torch":
            torch.load(path, weights_only=False)
        else:
            pickle.loads(path.read_bytes())
        assert marker.exists(), layout


# ----------------------------------------------------------------------------------------------------------
# Every command refuses a crafted file before anything in it runs


@pytest.mark.parametrize("command", ["animate", "render", "eval", "view"])
def test_avatar_commands_refuse_a_crafted_avatar_file(command, tmp_path):
    if command == "view":
        pytest.importorskip("viser")
    marker = tmp_path / "ran"
    crafted = _craft(tmp_path / "fit" / "avatar.pt", marker, tag=AVATAR_FORMAT)
    arguments = {"animate": ["-o", tmp_path / "out.usdc", "--motion", DEMO / "train"],
                 "render": ["-o", tmp_path / "frames", "--motion", DEMO / "train"],
                 "eval": [DEMO / "train"],
                 "view": ["--port", "0"]}[command]
    code, err = _run(command, [tmp_path / "fit", *arguments], tmp_path)
    _assert_refused_unpickling(code, err, crafted)
    assert "(a reference to getattr)" in err  # what torch.save wrote for Path.touch: getattr(Path, "touch")
    assert not marker.exists()


def test_fit_resume_refuses_a_crafted_checkpoint(tmp_path):
    marker = tmp_path / "ran"
    crafted = _craft(tmp_path / "out" / "checkpoint.pt", marker, tag=CHECKPOINT_FORMAT)
    code, err = _run("fit", [DEMO / "train", "-o", tmp_path / "out", "--resume", *FIT], tmp_path)
    _assert_refused_unpickling(code, err, crafted)
    assert not marker.exists()
    assert not (tmp_path / "out" / "avatar.pt").exists()


def test_the_fit_many_worker_refuses_a_crafted_checkpoint(tmp_path):
    """The body of a ``warpavatar-fit-many`` Ray task resumes the subject's checkpoint: a crafted one makes the
    subject fail with one line, and nothing in it runs."""
    marker = tmp_path / "ran"
    crafted = _craft(tmp_path / "out" / "checkpoint.pt", marker, tag=CHECKPOINT_FORMAT)
    result = fit_subject(BatchSubject("robot", DEMO), tmp_path / "out", config=preset("quick"), device="cpu",
                         preset_name="quick", evaluate=False)
    assert result["status"] == "failed"
    assert result["error"] == (f"{crafted}: the checkpoint holds objects other than tensors and plain containers "
                               "(a reference to getattr) and was not loaded (nothing in it ran)")
    assert not marker.exists()


# protocols below 4 pickle Path.touch as getattr(Path, "touch"); 4 and up frame the pickle (opcode 149), which the
# weights-only unpickler refuses before it reads any further
@pytest.mark.parametrize("layout, refused", [("torch", "a reference to getattr"),
                                              ("pickle2", "a reference to getattr"),
                                              ("pickle4", "pickle opcode 149")])
def test_loaders_refuse_bare_pickles_and_torch_files_alike(layout, refused, tmp_path):
    marker = tmp_path / "ran"
    avatar = _craft(tmp_path / "avatar.pt", marker, tag=AVATAR_FORMAT, layout=layout)
    with pytest.raises(ValueError) as raised:
        Avatar.load(avatar)
    assert str(raised.value) == (f"{avatar}: the avatar file holds objects other than tensors and plain containers "
                                 f"({refused}) and was not loaded (nothing in it ran)")
    checkpoint = _craft(tmp_path / "checkpoint.pt", marker, tag=CHECKPOINT_FORMAT, layout=layout)
    for mmap in (False, True):  # the fit-many worker maps the file to read its step
        with pytest.raises(ValueError, match=rf"^{checkpoint}: the checkpoint holds objects other than tensors"):
            read_checkpoint(checkpoint, mmap=mmap)
    assert not marker.exists()


def test_an_avatar_file_or_checkpoint_holding_no_dict_is_one_line(tmp_path, capsys):
    torch.save([torch.zeros(3)], tmp_path / "avatar.pt")
    code, _, err = run_command(eval_cli.main, [tmp_path, DEMO / "train"], capsys)
    assert_bad_input(code, err, tmp_path / "avatar.pt")
    assert err.strip() == f"error: {tmp_path / 'avatar.pt'}: not a warpavatar avatar file: it holds a list, not a dict"
    torch.save({"format": AVATAR_FORMAT}, tmp_path / "avatar.pt")
    code, _, err = run_command(eval_cli.main, [tmp_path, DEMO / "train"], capsys)
    assert_bad_input(code, err, tmp_path / "avatar.pt", "a damaged or incomplete avatar file (missing 'skeleton')")
    torch.save((1, 2), tmp_path / "checkpoint.pt")
    with pytest.raises(ValueError, match=r"checkpoint.pt: not a warpavatar checkpoint: it holds a tuple, not a dict$"):
        read_checkpoint(tmp_path / "checkpoint.pt")
    torch.save({"format": CHECKPOINT_FORMAT, "step": 3}, tmp_path / "checkpoint.pt")
    with pytest.raises(ValueError, match=r"checkpoint.pt: a damaged or incomplete checkpoint \(missing 'config', "):
        read_checkpoint(tmp_path / "checkpoint.pt")


# ----------------------------------------------------------------------------------------------------------
# Real files load; --resume refuses what it cannot continue


@pytest.fixture(scope="module")
def finished_fit(tmp_path_factory):
    """The output folder of a finished tiny fit of the demo's training folder (21 steps)."""
    output = tmp_path_factory.mktemp("finished") / "out"
    assert fit.main([str(argument) for argument in [DEMO / "train", "-o", output, *FIT]]) == 0
    return output


def _copy_fit(finished_fit, tmp_path):
    return pathlib.Path(shutil.copytree(finished_fit, tmp_path / "out"))


def _video_folder_like_the_demo(path, *, edit_poses=None, edit_skeleton=None):
    """A video folder at ``path`` sharing the demo's frames and masks (links), with its own copies of the other
    files, which ``edit_poses(arrays)`` / ``edit_skeleton(json)`` may change."""
    source = DEMO / "train"
    path.mkdir(parents=True)
    for name in ("frames", "masks"):
        (path / name).symlink_to(source / name, target_is_directory=True)
    for name in ("meta.json", "cameras.json", "skeleton.json", "poses.npz"):
        shutil.copy(source / name, path / name)
    if edit_poses is not None:
        arrays = dict(np.load(path / "poses.npz"))
        edit_poses(arrays)
        np.savez(path / "poses.npz", **arrays)
    if edit_skeleton is not None:
        skeleton = json.loads((path / "skeleton.json").read_text())
        edit_skeleton(skeleton)
        (path / "skeleton.json").write_text(json.dumps(skeleton))
    return path


def test_a_real_avatar_and_checkpoint_load(finished_fit):
    avatar = Avatar.load(finished_fit)
    assert avatar.joint_count == 41 and avatar.gaussians.count > 0
    state = read_checkpoint(finished_fit / "checkpoint.pt")
    assert state["format"] == CHECKPOINT_FORMAT and state["step"] == 21
    training = state["training"]
    assert training["folder"] == str((DEMO / "train").resolve())
    assert training["frame_count"] == 50 and training["image_size"] == [32, 32]
    assert training["skeleton"]["names"] == avatar.skeleton.names
    assert training["skeleton"]["parents"] == avatar.skeleton.parents.tolist()
    assert read_checkpoint(finished_fit / "checkpoint.pt", mmap=True)["step"] == 21
    # every tensor and container in both files is what the weights-only unpickler rebuilds
    torch.load(finished_fit / "avatar.pt", weights_only=True)


def test_resume_on_another_video_folder_is_refused(finished_fit, tmp_path, capsys):
    output = _copy_fit(finished_fit, tmp_path)
    stamp = (output / "avatar.pt").stat().st_mtime_ns

    def move_up(arrays):
        arrays["bone_transforms"][:, :, 2, 3] += 0.01
        arrays["joint_positions"][..., 2] += 0.01

    other = _video_folder_like_the_demo(tmp_path / "other", edit_poses=move_up)
    code, _, err = run_command(fit.main, [other, "-o", output, "--resume", *FIT], capsys)
    assert_bad_input(code, err)
    assert err.strip() == (f"error: {output / 'checkpoint.pt'}: the checkpoint was made on another video folder, "
                           f"{(DEMO / 'train').resolve()} (other poses), not {other.resolve()}; resume on that folder, "
                           "or start over with --overwrite or in a new output folder")
    assert (output / "avatar.pt").stat().st_mtime_ns == stamp


def test_resume_with_another_skeleton_is_refused(finished_fit, tmp_path, capsys):
    output = _copy_fit(finished_fit, tmp_path)

    def rename(skeleton):
        skeleton["joints"][5]["name"] = "Torso_renamed"

    other = _video_folder_like_the_demo(tmp_path / "other", edit_skeleton=rename)
    code, _, err = run_command(fit.main, [other, "-o", output, "--resume", *FIT], capsys)
    assert_bad_input(code, err)
    assert err.strip() == (f"error: {output / 'checkpoint.pt'}: the checkpoint was made on another video folder, "
                           f"{(DEMO / 'train').resolve()} (another skeleton: joint 5 is 'Torso_1' in the checkpoint "
                           f"vs 'Torso_renamed' given), not {other.resolve()}; resume on that folder, or start over "
                           "with --overwrite or in a new output folder")


def test_resume_of_a_finished_fit_with_other_options_is_refused(finished_fit, tmp_path, capsys):
    output = _copy_fit(finished_fit, tmp_path)
    stamp = (output / "avatar.pt").stat().st_mtime_ns
    code, out, err = run_command(fit.main, [DEMO / "train", "-o", output, "--resume", *FIT, "--sh-degree", "0"],
                                 capsys)
    assert_bad_input(code, err)
    assert err.strip() == (f"error: {output / 'checkpoint.pt'}: the fit there is finished (step 21 of 21) and was "
                           "made with other options (--sh-degree: 1 in the checkpoint vs 0 given); resume with the "
                           "checkpoint's options, or start over with --overwrite or in a new output folder")
    assert "done" not in out
    assert (output / "avatar.pt").stat().st_mtime_ns == stamp


def test_resume_accepts_the_same_video_folder_at_another_path(finished_fit, tmp_path, capsys):
    """The folder's identity is its content: the same files moved elsewhere resume (here: a finished fit, whose
    outputs are written again)."""
    output = _copy_fit(finished_fit, tmp_path)
    moved = _video_folder_like_the_demo(tmp_path / "moved")
    code, out, err = run_command(fit.main, [moved, "-o", output, "--resume", *FIT], capsys)
    assert code == 0, err
    assert "done in" in out


def test_an_avatar_file_cannot_import_a_module_outside_warpavatar_and_its_extensions(tmp_path, monkeypatch):
    """A part's class path in an avatar file names the module to import: a module of neither warpavatar nor a
    package that registers extensions is refused before it is imported, so its top-level code never runs."""
    from warpavatar.model.parts import part_from_file_state

    marker = tmp_path / "ran"
    (tmp_path / "payload_module_for_a_test.py").write_text(
        f"import pathlib\npathlib.Path({str(marker)!r}).touch()\nclass Part:\n    pass\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    entry = {"type": "payload_module_for_a_test:Part", "state": {}}
    with pytest.raises(ValueError, match="neither in warpavatar nor in a package that registers"):
        part_from_file_state("garment", entry, device="cpu")
    assert not marker.exists()
    assert "payload_module_for_a_test" not in sys.modules
    for bad in ("", "os;x:y", 5):
        with pytest.raises(ValueError):
            part_from_file_state("garment", {"type": bad, "state": {}}, device="cpu")


def test_a_package_that_registers_extensions_may_name_its_part_classes(tmp_path, monkeypatch):
    """The same module is imported once a distribution declares an entry point of warpavatar's extension group
    in its top-level package (a third-party part loads as the built-in ones do)."""
    import importlib.metadata

    from warpavatar.model.parts import EXTENSION_ENTRY_POINT_GROUP, part_from_file_state

    (tmp_path / "third_party_parts_for_a_test.py").write_text("class Part:\n    pass\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    declared = importlib.metadata.EntryPoint(name="x", value="third_party_parts_for_a_test:Extension",
                                             group=EXTENSION_ENTRY_POINT_GROUP)
    monkeypatch.setattr(importlib.metadata, "entry_points",
                        lambda group=None: [declared] if group == EXTENSION_ENTRY_POINT_GROUP else [])
    with pytest.raises(ValueError, match="which is not an avatar part"):  # imported, then checked
        part_from_file_state("garment", {"type": "third_party_parts_for_a_test:Part", "state": {}}, device="cpu")
    assert "third_party_parts_for_a_test" in sys.modules
