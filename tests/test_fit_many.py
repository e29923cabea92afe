"""``warpavatar-fit-many`` on a local Ray instance of 2 CPUs: tiny subjects land in their folders, a bad one fails
alone, a worker killed mid-fit is retried and resumes to the uninterrupted result, and a re-run skips what is
finished."""

import csv
import json
import shutil
import subprocess
import sys

import pytest
import torch

from warpavatar import data
from warpavatar.batch import DONE_NAME, SUMMARY_NAME, read_subjects
from warpavatar.cli import fit_many
from warpavatar.model import Avatar

# tiny fits: 30 steps on 6 frames at 32x32, a checkpoint every 10 steps
TINY = ["--preset", "quick", "--iterations", "30", "--image-scale", "0.25", "--max-train-frames", "6",
        "--init-points-per-bone", "20", "--init-carve-candidates", "5000", "--init-carve-points", "500",
        "--sh-degree", "1", "--grid-cells", "12", "--grid-min-cells", "6", "--field-hidden", "16",
        "--field-layers", "2", "--field-warmup-steps", "10", "--gaussian-only-steps", "15", "--densify-from", "10",
        "--densify-until", "25", "--densify-every", "10", "--checkpoint-every", "10", "--log-every", "10",
        "--preview-frames", "1", "--no-progress"]


def _summary(out_root):
    return {result["subject"]: result for result in
            json.loads((out_root / f"{SUMMARY_NAME}.json").read_text())["subjects"]}


def _subject(root, name):
    """A subject called ``name``: a link to the demo subject (train/, a novel view, a novel pose)."""
    (root / name).symlink_to(data.demo_subject_path(), target_is_directory=True)
    return root / name


def _tensors(state, prefix=""):
    """Every tensor in a nested dict/list, by its path."""
    if isinstance(state, torch.Tensor):
        return {prefix: state}
    items = state.items() if isinstance(state, dict) else enumerate(state) if isinstance(state, (list, tuple)) else ()
    return {path: tensor for key, value in items for path, tensor in _tensors(value, f"{prefix}/{key}").items()}


@pytest.fixture(scope="module")
def ray_cluster():
    ray = pytest.importorskip("ray")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield ray
    ray.shutdown()


@pytest.fixture(scope="module")
def batch(ray_cluster, tmp_path_factory):
    """Two good subjects (one named in a list file) and one whose cameras.json is broken, fitted and evaluated."""
    root = tmp_path_factory.mktemp("subjects")
    alice, bob = _subject(root, "alice"), _subject(root, "bob")
    broken = root / "broken"
    shutil.copytree(data.demo_subject_path() / "train", broken / "train")
    (broken / "train" / "cameras.json").write_text("{ not json")
    (root / "more.txt").write_text("# subjects of day two\nbob\n\nbroken\n")
    out_root = tmp_path_factory.mktemp("out")
    status = fit_many.main([str(alice), str(root / "more.txt"), "-o", str(out_root), "--eval", *TINY])
    return root, out_root, status


def test_two_subjects_land_in_their_folders_and_a_bad_one_fails_alone(batch):
    _, out_root, status = batch
    assert status == 1  # one subject failed
    summary = _summary(out_root)
    assert list(summary) == ["alice", "bob", "broken"]
    for name in ("alice", "bob"):
        result = summary[name]
        assert result["status"] == "done" and result["attempts"] == 1 and result["steps"] == 30, result
        for file in ("avatar.pt", "canonical.ply", "checkpoint.pt", "train_log.jsonl", "eval.json", DONE_NAME):
            assert (out_root / name / file).is_file(), (name, file)
        avatar = Avatar.load(out_root / name)
        assert avatar.gaussians.count == result["gaussians"] > 0
        assert set(result["eval"]) == {"novel_view/cam_090", "novel_pose/dance_cam000"}
        assert all(5.0 < metrics["psnr_masked"] < 60.0 for metrics in result["eval"].values()), result["eval"]
    broken = summary["broken"]
    assert broken["status"] == "failed" and "cameras.json" in broken["error"], broken
    assert broken["attempts"] == 1  # an input error is not retried
    assert not (out_root / "broken" / "avatar.pt").exists()
    with open(out_root / f"{SUMMARY_NAME}.csv", newline="") as f:
        rows = {row["subject"]: row for row in csv.DictReader(f)}
    assert rows["alice"]["status"] == "done" and float(rows["alice"]["novel_view/cam_090 psnr_masked"]) > 5.0
    assert rows["broken"]["status"] == "failed" and rows["broken"]["novel_view/cam_090 psnr_masked"] == ""


def test_a_killed_worker_is_retried_and_resumes_to_the_uninterrupted_result(batch, tmp_path, monkeypatch):
    _, first_out, _ = batch
    carol = _subject(tmp_path, "carol")
    out_root = tmp_path / "out"
    # the first attempt dies (SIGKILL) after step 25: steps 21-25 are lost, the retry resumes from step 20
    monkeypatch.setenv(fit_many.TEST_KILL_VARIABLE, "carol:25")
    assert fit_many.main([str(carol), "-o", str(out_root), "--max-retries", "1", *TINY]) == 0
    result = _summary(out_root)["carol"]
    assert result["status"] == "done" and result["attempts"] == 2 and result["resume_step"] == 20, result
    steps = [json.loads(line).get("step") for line in (out_root / "carol" / "train_log.jsonl").read_text().splitlines()]
    assert steps.count(20) == 1 and steps.count(30) == 1  # the killed attempt had logged step 20, not 30
    # the same fit as alice's, which ran uninterrupted: equal bit for bit
    resumed = torch.load(out_root / "carol" / "avatar.pt", weights_only=True)
    whole = torch.load(first_out / "alice" / "avatar.pt", weights_only=True)
    whole_tensors, resumed_tensors = _tensors(whole), _tensors(resumed)
    assert whole_tensors.keys() == resumed_tensors.keys() and len(whole_tensors) > 5
    for name, value in whole_tensors.items():
        assert torch.equal(value, resumed_tensors[name]), name


def test_a_rerun_skips_finished_subjects_and_force_fits_again_on_a_joined_cluster(ray_cluster, batch, tmp_path):
    root, first_out, _ = batch
    out_root = tmp_path / "out"
    shutil.copytree(first_out, out_root)
    stamp = (out_root / "alice" / "avatar.pt").stat().st_mtime_ns
    assert fit_many.main([str(root / "alice"), str(root / "bob"), "-o", str(out_root), *TINY]) == 0
    summary = _summary(out_root)
    assert [summary[name]["status"] for name in ("alice", "bob")] == ["skipped", "skipped"]
    assert summary["alice"]["gaussians"] > 0 and summary["alice"]["eval"]  # the earlier run's result
    assert (out_root / "alice" / "avatar.pt").stat().st_mtime_ns == stamp

    # finished with other options: not skipped as if it were this fit, not fitted over either
    assert fit_many.main([str(root / "alice"), "-o", str(out_root), *TINY, "--lambda-ssim", "0.3"]) == 1
    result = _summary(out_root)["alice"]
    assert result["status"] == "failed" and "(lambda_ssim)" in result["error"] and "--force" in result["error"]
    assert (out_root / "alice" / "avatar.pt").stat().st_mtime_ns == stamp

    # --force fits it again; this run is another process that joins the running cluster (--ray-address)
    address = ray_cluster.get_runtime_context().gcs_address
    command = [sys.executable, "-m", "warpavatar.cli.fit_many", str(root / "alice"), "-o", str(out_root), "--force",
               "--ray-address", address, *TINY]
    run = subprocess.run(command, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    assert "alice: done in" in run.stdout and "on Ray (0 GPUs, 2 CPUs)" in run.stdout, run.stdout
    result = _summary(out_root)["alice"]
    assert result["status"] == "done" and result["resume_step"] == 0 and result["eval"] == {}
    assert (out_root / "alice" / "avatar.pt").stat().st_mtime_ns != stamp


def test_options_are_checked_before_any_task_starts(ray_cluster, tmp_path, capsys):
    subject = _subject(tmp_path, "dave")
    status = fit_many.main([str(subject), "-o", str(tmp_path / "out"), *TINY, "--secondary-from", "5"])
    assert status == 2
    assert "--secondary-from is an option of --secondary-motion" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_subjects_from_folders_and_list_files_and_a_name_clash(tmp_path):
    for folder in ("day1/eve", "elsewhere/frank"):
        (tmp_path / folder).mkdir(parents=True)
    (tmp_path / "day1" / "list.txt").write_text(f"eve\n# a comment\n\n{tmp_path / 'elsewhere' / 'frank'}\n")
    subjects = read_subjects([tmp_path / "day1" / "list.txt", tmp_path / "grace"])
    assert [subject.name for subject in subjects] == ["eve", "frank", "grace"]
    assert subjects[0].path == tmp_path / "day1" / "eve" and subjects[1].path == tmp_path / "elsewhere" / "frank"
    with pytest.raises(ValueError, match="two subjects are called 'eve'"):
        read_subjects([tmp_path / "day1" / "list.txt", tmp_path / "other" / "eve"])
    with pytest.raises(ValueError, match="grace: the subject is given twice"):
        read_subjects([tmp_path / "grace", tmp_path / "day1" / ".." / "grace"])


def test_without_ray_the_command_says_how_to_install_it(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray now fails as if it were not installed
    assert fit_many.main([str(tmp_path), "-o", str(tmp_path / "out")]) == 2
    assert 'pip install -e ".[cluster]"' in capsys.readouterr().err
