"""What the commands print about a fit and its scores: one resolution rule for every reported score (the demo's
report and fit-many's agree), evaluation timings with render and metrics apart, the fit's closing line of next
commands, the training motion as the default ``--motion``, and a CPU command's stderr free of Warp's
CUDA-driver warning."""

import contextlib
import io
import json
import re
import shutil
import subprocess
import sys

import pytest

from warpavatar import data
from warpavatar.batch.job import fit_subject
from warpavatar.batch.report import one_line_result
from warpavatar.batch.subjects import BatchSubject
from warpavatar.cli import eval as eval_cli
from warpavatar.cli import fit
from warpavatar.fit.config import FitConfig

DEMO = data.demo_subject_path()

# the demo preset cut to a few steps: the avatar is poor, but every reporting path runs
TINY_DEMO = ["--demo", "--device", "cpu", "--iterations", "3", "--field-warmup-steps", "2",
             "--init-carve-candidates", "2000", "--no-progress", "--preview-frames", "1"]


@pytest.fixture(scope="module")
def demo_fit(tmp_path_factory):
    """``(output folder, what warpavatar-fit --demo printed)`` of one tiny demo fit (trained at 64x64)."""
    output = tmp_path_factory.mktemp("demo") / "fit"
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        assert fit.main([*TINY_DEMO, "-o", str(output)]) == 0
    return output, printed.getvalue()


def test_demo_report_and_fit_many_report_agree_on_number_and_resolution(demo_fit, tmp_path):
    output, printed = demo_fit
    demo_lines = {line.split(":")[0].strip(): line.strip() for line in printed.splitlines()
                  if line.startswith("  novel_")}
    assert set(demo_lines) == {"novel_view/cam_090", "novel_pose/dance_cam000"}
    # fit-many's path on the same avatar: a copy of the fit resumed at its last step (nothing left to train)
    copy = shutil.copytree(output, tmp_path / "robot")
    config = FitConfig.from_dict(json.loads((output / "config.json").read_text()))
    result = fit_subject(BatchSubject("robot", DEMO), copy, config=config, device="cpu", preset_name="demo",
                         evaluate=True)
    assert result["status"] == "done", result
    line = one_line_result({**result, "wall_seconds": 1.0})
    for label, demo_line in demo_lines.items():
        demo_db = re.search(r"masked PSNR (\d+\.\d\d) dB", demo_line).group(1)
        assert demo_line.endswith(" at 64x64"), demo_line
        assert f"{label} {demo_db} dB" in line, (demo_line, line)
        assert result["eval"][label]["resolution"] == "64x64"
    assert line.endswith(" at 64x64"), line
    demo_json = json.loads((output / "demo_eval.json").read_text())
    for label, scores in demo_json.items():
        assert scores["psnr_masked"] == pytest.approx(result["eval"][label]["psnr_masked"], abs=1e-9)


def test_fit_ends_with_the_next_commands_and_no_warning_style_lines(demo_fit):
    output, printed = demo_fit
    lines = printed.strip().splitlines()
    assert lines[-1] == (f"next: warpavatar-view {output} | warpavatar-render {output} --orbit -o turntable.mp4 | "
                         f"warpavatar-animate {output} -o avatar.usdc")
    assert not any("poses used as given" in line or "warning" in line.lower() for line in lines)


def test_eval_prints_render_and_metric_times_apart_at_the_training_resolution(demo_fit, tmp_path, capsys):
    output, _ = demo_fit
    results_path = tmp_path / "eval.json"
    assert eval_cli.main([str(output), str(DEMO / "novel_view" / "cam_090"), "--device", "cpu", "--no-progress",
                          "--json", str(results_path)]) == 0
    printed = capsys.readouterr().out.splitlines()
    scores = [line for line in printed if line.startswith("cam_090: ")]
    timings = [line for line in printed if line.startswith("  ")]
    assert len(scores) == 1 and scores[0].endswith(" at 64x64"), printed  # config.json's image_scale 0.5
    assert len(timings) == 1 and re.fullmatch(r"  20 frames; per frame: render \d+ ms, metrics \d+ ms", timings[0])
    result = json.loads(results_path.read_text())
    assert result["resolution"] == "64x64" and "seconds_per_frame" not in result
    assert 0.0 <= result["floater_share"] <= 1.0 and all(0.0 <= frame["floater_share"] <= 1.0
                                                        for frame in result["frames"])
    assert f"masked SSIM {result['ssim_masked']:.4f}, floaters {100 * result['floater_share']:.2f}%, PSNR" in scores[0]
    assert result["render_seconds_per_frame"] > 0 and result["metric_seconds_per_frame"] > 0
    assert f"{1000 * result['render_seconds_per_frame']:.0f} ms" in timings[0]
    assert f"{1000 * result['metric_seconds_per_frame']:.0f} ms" in timings[0]
    # --scale still chooses another resolution, and says so
    assert eval_cli.main([str(output), str(DEMO / "novel_view" / "cam_090"), "--device", "cpu", "--no-progress",
                          "--scale", "1"]) == 0
    assert " at 128x128\n" in capsys.readouterr().out


def test_eval_refuses_frames_smaller_than_the_ssim_window_in_one_line(demo_fit, capsys):
    output, _ = demo_fit
    assert eval_cli.main([str(output), str(DEMO / "novel_view" / "cam_090"), "--device", "cpu", "--no-progress",
                          "--scale", "0.05"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert "its frames are 6x6 pixels at this scale, smaller than SSIM's 11x11-pixel window" in err


@pytest.mark.parametrize("command", ["animate", "render"])
def test_animate_and_render_default_to_the_training_motion(demo_fit, tmp_path, monkeypatch, command):
    from warpavatar.cli import animate, render
    from warpavatar.io import motion as motion_module

    output, _ = demo_fit
    read = []
    load_motion = motion_module.load_motion
    monkeypatch.setattr(motion_module, "load_motion", lambda path, *a, **k: read.append(path) or load_motion(
        path, *a, **k))
    main, target = (animate.main, tmp_path / "avatar.usdc") if command == "animate" else (
        render.main, tmp_path / "frames")
    extra = ["--size", "32"] if command == "render" else []
    assert main([str(output), "-o", str(target), "--frames", "0:2", "--no-progress", "--device", "cpu", *extra]) == 0
    assert read == [output / "training_poses.npz"]
    if command == "render":
        assert sorted(path.name for path in target.glob("*.png")) == ["000000.png", "000001.png"]
    else:
        assert target.is_file()


@pytest.mark.parametrize("command", ["animate", "render"])
def test_missing_training_motion_is_one_line_naming_the_file(demo_fit, tmp_path, capsys, command):
    from warpavatar.cli import animate, render

    output, _ = demo_fit
    bare = tmp_path / "bare"
    bare.mkdir()
    shutil.copy(output / "avatar.pt", bare / "avatar.pt")
    main = animate.main if command == "animate" else render.main
    assert main([str(bare), "-o", str(tmp_path / "out.mp4" if command == "render" else tmp_path / "out.usdc"),
                 "--no-progress", "--device", "cpu"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert err.startswith(f"error: {bare / 'training_poses.npz'}: no such file") and "give --motion" in err


def test_motion_help_names_the_training_motion_default():
    from warpavatar.cli import animate, render

    for parser in (animate.build_parser(), render.build_parser()):
        motion = next(action for action in parser._actions if action.dest == "motion")
        assert not motion.required and motion.default is None
        assert "training_poses.npz in the fit's output folder" in motion.help


def test_a_cpu_command_prints_no_cuda_driver_warning(demo_fit):
    from warpavatar._src import warp_utils

    output, _ = demo_fit
    command = [sys.executable, "-m", "warpavatar.cli.eval", str(output), str(DEMO / "novel_pose" / "dance_cam000"),
               "--device", "cpu", "--no-progress"]
    finished = subprocess.run(command, capture_output=True, text=True, timeout=600)
    assert finished.returncode == 0, finished.stderr
    assert "CUDA driver" not in finished.stderr and "warning" not in finished.stderr.lower(), finished.stderr
    assert " at 64x64" in finished.stdout
    if not warp_utils._CUDA_DRIVER_LOADABLE:  # the warning the command silences is there without it
        bare = subprocess.run([sys.executable, "-c", "import warp; warp.config.log_level = warp.LOG_WARNING; "
                               "warp.init()"], capture_output=True, text=True, timeout=600)
        assert "Could not find or load the NVIDIA CUDA driver" in bare.stderr
