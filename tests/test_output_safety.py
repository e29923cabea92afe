"""Outputs never destroy what the project did not write: the commands refuse a user's folder and the folders the
user works in, leave files that merely look like temporary ones alone, let one writer at a time write an output,
and turn a full disk into one line with nothing left behind (warpavatar.io.output_files).

The commands run as subprocesses where their exit status and stderr are checked. A full disk is simulated by a
patched ``os.write`` (every file the project writes goes through it) or a failing USD save; where this machine
lets the test mount a tiny tmpfs, a real full disk too.
"""

import errno
import json
import os
import re
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from warpavatar import data
from warpavatar.io import output_files
from warpavatar.io.output_files import DiskFullError, lock_path, output_lock

DEMO = data.demo_subject_path()
ROOT = Path(__file__).resolve().parents[1]
MOTION = ["--motion", str(DEMO / "train"), "--frames", "0:3", "--no-progress", "--device", "cpu"]

# Run a command with os.write failing (ENOSPC) for files below FOLDER whose name holds TEXT, once BUDGET bytes of
# them were written: a disk with BUDGET bytes free. argv: FOLDER TEXT BUDGET MODULE ARGUMENTS...
FULL_DISK = """
import errno, os, runpy, sys
folder, text, budget, module = os.path.realpath(sys.argv[1]), sys.argv[2], int(sys.argv[3]), sys.argv[4]
real_write, spent = os.write, [0]
def write(descriptor, data):
    try:
        path = os.readlink(f"/proc/self/fd/{descriptor}")
    except OSError:
        path = ""
    if path.startswith(folder + os.sep) and text in os.path.basename(path):
        if spent[0] + len(data) > budget:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        spent[0] += len(data)
    return real_write(descriptor, data)
os.write = write
sys.argv = [module, *sys.argv[5:]]
runpy.run_module(module, run_name="__main__", alter_sys=True)
"""

# Run a command with every USD save after the first failing as usd-core reports a full disk. argv: MODULE ARGS...
FULL_DISK_USD = """
import runpy, sys
from pxr import Sdf, Tf
real_save, saves = Sdf.Layer.Save, [0]
def save(layer, *args, **kwargs):
    saves[0] += 1
    if saves[0] > 1:
        Tf.RaiseRuntimeError("Failed writing usdc data: Error occurred writing file: No space left on device")
    return real_save(layer, *args, **kwargs)
Sdf.Layer.Save = save
module = sys.argv[1]
sys.argv = [module, *sys.argv[2:]]
runpy.run_module(module, run_name="__main__", alter_sys=True)
"""


def _environment():
    return dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))


def run_cli(module: str, arguments, *, cwd, preamble: str | None = None, preamble_arguments=()):
    """(exit status, stdout, stderr) of ``python -m module arguments`` in ``cwd`` (or of ``preamble`` run
    with ``preamble_arguments``, the module and the arguments)."""
    arguments = [str(argument) for argument in arguments]
    command = ([sys.executable, "-m", module, *arguments] if preamble is None else
               [sys.executable, "-c", preamble, *map(str, preamble_arguments), module, *arguments])
    done = subprocess.run(command, cwd=cwd, env=_environment(), capture_output=True, text=True, timeout=600)
    return done.returncode, done.stdout, done.stderr


def error_line(code: int, err: str) -> str:
    """The one line on stderr of a refused command (exit status 2, no traceback); warnings before it aside."""
    lines = [line for line in err.strip().splitlines() if not line.startswith("warning:")]
    assert code == 2 and len(lines) == 1 and "Traceback" not in err, (code, err)
    return lines[0]


def listing(folder: Path) -> list[str]:
    """Every entry below ``folder``, hidden ones included, as sorted relative paths."""
    return sorted(path.relative_to(folder).as_posix() for path in folder.rglob("*"))


@pytest.fixture
def work(tmp_path):
    """An empty working directory for the command."""
    folder = tmp_path / "work"
    folder.mkdir()
    return folder


# ----------------------------------------------------------------------------------------------------------
# The module itself


def test_temporary_names_are_unique_and_keep_a_suffix_where_asked(tmp_path):
    first, second = (output_files.temporary_path(tmp_path / "a.usdc", suffix=".usdc") for _ in range(2))
    assert first != second and first.parent == tmp_path
    assert re.fullmatch(rf"a\.tmp-{os.getpid()}-[0-9a-f]{{12}}\.usdc", first.name)
    assert re.fullmatch(rf"clip\.tmp-{os.getpid()}-[0-9a-f]{{12}}", output_files.temporary_path(tmp_path / "clip").name)
    assert output_files.is_temporary_name(first.name, "a.usdc")
    assert not output_files.is_temporary_name("a.tmp.usdc", "a.usdc")
    assert not output_files.is_temporary_name("clip.tmp", "clip")


def test_a_failed_atomic_write_removes_only_its_temporary_file(tmp_path):
    (tmp_path / "a.json.tmp").write_text("mine")
    output_files.write_json_atomic(tmp_path / "a.json", {"first": 1})
    with pytest.raises(RuntimeError, match="half-way"):
        with output_files.atomic_open(tmp_path / "a.json", "w") as stream:
            stream.write("{")
            raise RuntimeError("half-way")
    assert listing(tmp_path) == ["a.json", "a.json.tmp"]
    assert json.loads((tmp_path / "a.json").read_text()) == {"first": 1}
    assert (tmp_path / "a.json.tmp").read_text() == "mine"


def _fail_writes_below(monkeypatch, folder: Path, *, budget: int = 0):
    """Make ``os.write`` raise ENOSPC for files below ``folder`` once ``budget`` bytes of them were written."""
    real_write, spent = os.write, [0]
    folder = os.path.realpath(folder)

    def write(descriptor, payload):
        try:
            path = os.readlink(f"/proc/self/fd/{descriptor}")
        except OSError:
            path = ""
        if path.startswith(folder + os.sep):
            if spent[0] + len(payload) > budget:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            spent[0] += len(payload)
        return real_write(descriptor, payload)

    monkeypatch.setattr(os, "write", write)


def test_a_full_disk_during_a_checkpoint_save_leaves_the_previous_one_and_no_temporary_file(tmp_path, monkeypatch):
    from warpavatar.fit.checkpoint import save_checkpoint

    path = tmp_path / "checkpoint.pt"
    save_checkpoint(path, {"step": 1, "weights": torch.zeros(10)})
    _fail_writes_below(monkeypatch, tmp_path)
    with pytest.raises(DiskFullError) as raised:  # torch wraps the OSError in a RuntimeError: it is found again
        save_checkpoint(path, {"step": 2, "weights": torch.zeros(100_000)})
    assert raised.value.errno == errno.ENOSPC
    assert re.fullmatch(rf"{re.escape(str(path))}: not written: no space is left on the disk \([\d.]+ \w+ free in "
                        rf"{re.escape(str(tmp_path))}\); free some space or write it elsewhere", str(raised.value))
    assert listing(tmp_path) == ["checkpoint.pt"] and torch.load(path)["step"] == 1


def test_a_second_writer_of_one_output_is_refused_naming_the_first(tmp_path):
    output = tmp_path / "clip.mp4"
    with output_lock(output, flag="-o") as lock:
        assert lock == lock_path(output) == tmp_path / ".clip.mp4.warpavatar-lock"
        assert lock.read_text() == f"pid {os.getpid()} on {socket.gethostname()}\n"
        with pytest.raises(output_files.OutputBusyError) as raised:
            with output_lock(output, flag="-o"):
                pass
        assert str(raised.value) == (f"-o {output}: another warpavatar process (pid {os.getpid()} on "
                                     f"{socket.gethostname()}) is writing it; wait for it to end or give another -o")
    assert listing(tmp_path) == []  # released: the lock file is gone
    # a lock file a killed writer left is taken over, with the temporary files it left for that output
    lock.write_text("pid 1 on elsewhere\n")
    leftover = output_files.temporary_path(output, suffix=".mp4")
    leftover.write_bytes(b"half")
    (tmp_path / "clip.tmp.mp4").write_bytes(b"mine")
    with output_lock(output, flag="-o"):
        assert sorted(path.name for path in tmp_path.iterdir()) == [".clip.mp4.warpavatar-lock", "clip.tmp.mp4"]
    assert listing(tmp_path) == ["clip.tmp.mp4"]


# ----------------------------------------------------------------------------------------------------------
# warpavatar-render: folders that are not its own, the folders the user works in


def test_render_refuses_a_folder_of_photos_even_with_overwrite(avatar_dir, work):
    photos = work / "photos"
    photos.mkdir()
    for name in ("beach.jpg", "family.jpg"):
        (photos / name).write_bytes(b"not warpavatar's")
    for extra in ([], ["--overwrite"]):
        code, _, err = run_cli("warpavatar.cli.render", [avatar_dir, *MOTION, "-o", "photos", *extra], cwd=work)
        assert error_line(code, err) == (
            "error: -o photos: the folder exists and holds files warpavatar did not write (beach.jpg, family.jpg); "
            "choose another -o (it is never replaced, even with --overwrite)")
    assert listing(work) == ["photos", "photos/beach.jpg", "photos/family.jpg"]


@pytest.mark.parametrize("given, what, example", [
    (".", "the working directory", "warpavatar-out"),
    ("..", "an ancestor of the working directory", "../warpavatar-out"),
    ("PWD", "the working directory", "PWD/warpavatar-out"),
])
def test_render_refuses_the_working_directory_and_its_ancestors(avatar_dir, work, given, what, example):
    given, example = given.replace("PWD", str(work)), example.replace("PWD", str(work))
    (work / "notes.txt").write_text("mine")
    code, _, err = run_cli("warpavatar.cli.render", [avatar_dir, *MOTION, "-o", given], cwd=work)
    assert error_line(code, err) == (f"error: -o {given}: is {what}; an output must not replace it: give a new path "
                                     f"below it (e.g. -o {example})")
    assert listing(work.parent) == ["work", "work/notes.txt"]


def test_every_command_refuses_the_folders_the_user_works_in(avatar_dir, work, monkeypatch, capsys):
    from warpavatar.cli import animate, eval as eval_cli, fit

    monkeypatch.chdir(work)
    home = Path.home()
    for main, arguments in (
            (animate.main, [avatar_dir, *MOTION, "-o", ".."]),
            (fit.main, [DEMO / "train", "-o", ".", "--device", "cpu"]),
            (fit.main, [DEMO / "train", "-o", "/", "--device", "cpu"]),
            (eval_cli.main, [avatar_dir, DEMO / "novel_view" / "cam_090", "--save-renders", home, "--device", "cpu"])):
        assert main([str(argument) for argument in arguments]) == 2
        err = capsys.readouterr().err
        assert err.startswith("error: ") and err.count("\n") == 1 and "an output must not replace it" in err, err
    assert listing(work) == []


def test_render_replaces_its_own_frames_only_with_overwrite_and_only_when_they_are_alone(avatar_dir, work):
    code, out, err = run_cli("warpavatar.cli.render", [avatar_dir, *MOTION, "-o", "clip"], cwd=work)
    assert code == 0, err
    assert out.strip().splitlines()[-1] == "wrote clip (3 frames at 15 fps)"
    frames = ["000000.png", "000001.png", "000002.png"]
    assert listing(work) == ["clip", *(f"clip/{name}" for name in [".warpavatar-output", *frames])]
    assert (work / "clip" / ".warpavatar-output").read_text().splitlines() == ["render-frames", *frames]
    before = (work / "clip" / "000000.png").stat().st_mtime_ns
    code, _, err = run_cli("warpavatar.cli.render", [avatar_dir, *MOTION, "-o", "clip"], cwd=work)
    assert error_line(code, err) == ("error: -o clip: already exists (an earlier render-frames output); give "
                                     "--overwrite to replace it, or choose another -o")
    code, _, err = run_cli("warpavatar.cli.render", [avatar_dir, *MOTION, "-o", "clip", "--frames", "0:2",
                                                     "--overwrite"], cwd=work)
    assert code == 0, err
    assert listing(work) == ["clip", "clip/.warpavatar-output", "clip/000000.png", "clip/000001.png"]
    assert (work / "clip" / "000000.png").stat().st_mtime_ns != before
    (work / "clip" / "notes.txt").write_text("mine")
    code, _, err = run_cli("warpavatar.cli.render", [avatar_dir, *MOTION, "-o", "clip", "--overwrite"], cwd=work)
    assert error_line(code, err) == ("error: -o clip: holds files warpavatar did not write besides its render-frames "
                                     "(notes.txt); move them away or choose another -o")
    assert (work / "clip" / "notes.txt").read_text() == "mine"


# ----------------------------------------------------------------------------------------------------------
# Files named like the old fixed temporary names


def test_files_named_like_old_temporary_names_survive_an_export_and_a_render(avatar_dir, work):
    (work / "scene.tmp.usdc").write_bytes(b"my scene")
    (work / "clip.tmp").mkdir()
    (work / "clip.tmp" / "shot.png").write_bytes(b"my shot")
    (work / "clip.tmp.mp4").write_bytes(b"my video")
    for module, output in (("warpavatar.cli.animate", "scene.usdc"), ("warpavatar.cli.render", "clip"),
                           ("warpavatar.cli.render", "clip.mp4")):
        code, _, err = run_cli(module, [avatar_dir, *MOTION, "-o", output], cwd=work)
        assert code == 0, err
    assert [path for path in listing(work) if not path.startswith("clip/")] == [
        "clip", "clip.mp4", "clip.tmp", "clip.tmp.mp4", "clip.tmp/shot.png", "scene.tmp.usdc", "scene.usdc"]
    assert (work / "scene.tmp.usdc").read_bytes() == b"my scene"
    assert (work / "clip.tmp" / "shot.png").read_bytes() == b"my shot"
    assert (work / "clip.tmp.mp4").read_bytes() == b"my video"


# ----------------------------------------------------------------------------------------------------------
# One writer per output


def test_a_second_export_to_one_output_is_refused_naming_the_first_ones_pid(avatar_dir, work):
    with np.load(DEMO / "train" / "poses.npz") as archive:
        bones = archive["bone_transforms"]
    np.savez(work / "long.npz", bone_transforms=np.tile(bones, (200, 1, 1, 1)), fps=np.float32(30.0))
    arguments = [avatar_dir, "--motion", "long.npz", "-o", "anim.usdc", "--device", "cpu", "--no-progress"]
    first = subprocess.Popen([sys.executable, "-m", "warpavatar.cli.animate", *map(str, arguments)], cwd=work,
                             env=_environment(), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.time() + 120
        while not list(work.glob("anim.tmp-*.usdc")):  # the first one holds the lock and writes
            assert first.poll() is None and time.time() < deadline, "the first export ended or never started"
            time.sleep(0.05)
        code, _, err = run_cli("warpavatar.cli.animate", [*arguments[:3], "-o", "anim.usdc", *MOTION[2:]], cwd=work)
        assert error_line(code, err) == (f"error: -o anim.usdc: another warpavatar process (pid {first.pid} on "
                                         f"{socket.gethostname()}) is writing it; wait for it to end or give "
                                         "another -o")
        assert first.poll() is None
    finally:
        first.kill()
        first.wait()
    # killed: its lock file and temporary file stay behind; the next export takes both over and removes them
    assert len(list(work.glob("anim.tmp-*.usdc"))) == 1 and (work / ".anim.usdc.warpavatar-lock").exists()
    code, _, err = run_cli("warpavatar.cli.animate", [avatar_dir, *MOTION, "-o", "anim.usdc"], cwd=work)
    assert code == 0, err
    assert listing(work) == ["anim.usdc", "long.npz"]


def test_a_second_fit_and_a_busy_fit_many_subject_are_refused(work):
    from warpavatar.batch.job import fit_subject
    from warpavatar.batch.subjects import BatchSubject

    output = work / "out"
    holder = f"pid {os.getpid()} on {socket.gethostname()}"
    with output_lock(output, flag="-o"):
        code, _, err = run_cli("warpavatar.cli.fit", [DEMO / "train", "-o", "out", "--device", "cpu"], cwd=work)
        assert error_line(code, err) == (f"error: -o out: another warpavatar process ({holder}) is writing it; wait "
                                         "for it to end or give another -o")
        result = fit_subject(BatchSubject("out", DEMO), output, config=None, device="cpu", preset_name="quick",
                             evaluate=False)
        assert result["status"] == "failed"
        assert result["error"] == (f"{output}: another warpavatar process ({holder}) is writing it; wait for it to "
                                   "end or give another output")
    assert listing(work) == []


# ----------------------------------------------------------------------------------------------------------
# Full disks


def test_a_full_disk_during_a_frames_render_is_one_line_and_leaves_nothing(avatar_dir, work):
    code, out, err = run_cli("warpavatar.cli.render", [avatar_dir, *MOTION, "-o", "clip", "--frames", "0:10"],
                             cwd=work, preamble=FULL_DISK, preamble_arguments=[work, ".png", 12_000])
    line = error_line(code, err)
    assert re.fullmatch(r"error: clip: not written: no space is left on the disk \(writing 0000\d\d\.png, [\d.]+ "
                        rf"(bytes|KiB) to write, [\d.]+ \w+ free in \.\); free some space or write it elsewhere",
                        line), line
    assert "wrote" not in out and listing(work) == []


def test_a_full_disk_during_a_usd_export_is_one_line_and_leaves_nothing(avatar_dir, work):
    (work / "anim.usdc").write_bytes(b"the previous export")
    code, _, err = run_cli("warpavatar.cli.animate", [avatar_dir, *MOTION, "-o", "anim.usdc"], cwd=work,
                           preamble=FULL_DISK_USD)
    line = error_line(code, err)
    assert re.fullmatch(r"error: anim\.usdc: not written: no space is left on the disk \([\d.]+ \w+ free in \.\); "
                        "free some space or write it elsewhere", line), line
    assert listing(work) == ["anim.usdc"] and (work / "anim.usdc").read_bytes() == b"the previous export"


def test_a_full_disk_during_a_fit_checkpoint_is_one_line_and_leaves_no_checkpoint(work):
    arguments = [DEMO / "train", "-o", "out", "--preset", "quick", "--image-scale", "0.25", "--max-train-frames",
                 "2", "--init-points-per-bone", "10", "--init-carve-candidates", "2000", "--init-carve-points", "200",
                 "--grid-cells", "8", "--grid-min-cells", "4", "--field-hidden", "16", "--field-layers", "1",
                 "--field-warmup-steps", "2", "--iterations", "2", "--checkpoint-every", "1", "--no-progress",
                 "--device", "cpu"]
    code, _, err = run_cli("warpavatar.cli.fit", arguments, cwd=work, preamble=FULL_DISK,
                           preamble_arguments=[work, "checkpoint.pt", 0])
    line = error_line(code, err)
    assert re.fullmatch(r"error: out/checkpoint\.pt: not written: no space is left on the disk \([\d.]+ \w+ free in "
                        r"out\); free some space or write it elsewhere", line), line
    names = listing(work / "out")
    assert not [name for name in names if "checkpoint" in name] and ".warpavatar-output" in names, names


def test_a_full_disk_during_eval_save_renders_leaves_no_folder(avatar_dir, work, monkeypatch, capsys):
    from warpavatar.cli import eval as eval_cli

    monkeypatch.chdir(work)
    _fail_writes_below(monkeypatch, work, budget=20_000)
    code = eval_cli.main([str(avatar_dir), str(DEMO / "novel_view" / "cam_090"), "--save-renders", "renders",
                          "--no-progress", "--device", "cpu"])
    line = error_line(code, capsys.readouterr().err)
    assert re.fullmatch(r"error: renders: not written: no space is left on the disk \(writing 0000\d\d\.png, .*\); "
                        "free some space or write it elsewhere", line), line
    assert listing(work) == []


@pytest.fixture
def tiny_disk(tmp_path):
    """A 512 KiB tmpfs mounted for the test (skipped where this process may not mount one)."""
    mount = tmp_path / "disk"
    mount.mkdir()
    try:
        subprocess.run(["mount", "-t", "tmpfs", "-o", "size=512k", "tmpfs", str(mount)], check=True,
                       capture_output=True, timeout=30)
    except (OSError, subprocess.SubprocessError):
        pytest.skip("cannot mount a tmpfs here (needs root)")
    try:
        yield mount
    finally:
        subprocess.run(["umount", str(mount)], check=False, capture_output=True, timeout=30)


def test_a_real_full_disk_for_png_frames_a_video_and_a_usd_export(avatar_dir, tiny_disk):
    filler = tiny_disk / "filler"
    # 8 KiB left: less than the H.264 video of 50 frames needs (about 18 KiB)
    filler.write_bytes(b"\0" * (os.statvfs(tiny_disk).f_bavail * os.statvfs(tiny_disk).f_frsize - 8 * 1024))
    for module, output in (("warpavatar.cli.render", "clip"), ("warpavatar.cli.render", "clip.mp4"),
                           ("warpavatar.cli.animate", "anim.usdc")):
        code, out, err = run_cli(module, [avatar_dir, *MOTION[:3], "0:50", *MOTION[4:], "-o", output],
                                 cwd=tiny_disk)
        line = error_line(code, err)
        assert re.fullmatch(rf"error: {re.escape(output)}: not written: no space is left on the disk \(.*free in "
                            r"\.\); free some space or write it elsewhere", line), line
        assert "wrote" not in out and sorted(path.name for path in tiny_disk.iterdir()) == ["filler"]
