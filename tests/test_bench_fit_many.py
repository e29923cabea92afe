"""Which GPU a batch's fit runs on (Ray's GPU ids and CUDA_VISIBLE_DEVICES faked, no GPU needed), the kernel
cache's compile turn, and tools/bench_fit_many.py on the CPU with tiny fits."""

import json
import os
import shutil
import socket
import subprocess
import sys
import time

import pytest
import torch
from conftest import TINY_FIT, load_tool

from warpavatar import data
from warpavatar.batch import gpus, runner
from warpavatar.batch.gpus import compiled_marker_name, first_compile_turn, task_cuda_device


@pytest.mark.parametrize("gpu_ids, visible, count, expected", [
    (["1"], "1", 1, "cuda:0"),  # Ray narrowed the visibility to the task's GPU: it is cuda:0
    ([3], "3", 1, "cuda:0"),  # integer ids, as older Ray versions give them
    (["GPU-5e1f"], "GPU-5e1f", 1, "cuda:0"),  # a node whose CUDA_VISIBLE_DEVICES names GPUs by UUID
    (["0", "2"], "0,2", 2, "cuda:0"),  # a fit of two GPUs runs on the first
    (["2"], None, 4, "cuda:2"),  # Ray left the visibility alone (RAY_EXPERIMENTAL_NOSET_CUDA_VISIBLE_DEVICES)
    (["3"], "1,3", 2, "cuda:1"),  # ... on a node started with CUDA_VISIBLE_DEVICES=1,3
])
def test_the_fit_runs_on_the_gpu_ray_gave_its_task(gpu_ids, visible, count, expected):
    assert task_cuda_device(gpu_ids, visible_devices=visible, device_count=count) == expected


@pytest.mark.parametrize("gpu_ids, visible, count, message", [
    ([], None, 4, "gave its task no GPU"),
    (["1"], "1", 0, "CUDA shows this worker none"),
    (["1"], "1", 4, "CUDA was initialized in the worker before Ray chose its GPU"),
    (["5"], "0,1", 2, "not among the GPUs"),
    (["2"], None, 2, "not among the GPUs"),
])
def test_a_task_that_cannot_know_its_gpu_fails_rather_than_share_another(gpu_ids, visible, count, message):
    with pytest.raises(RuntimeError, match=message):
        task_cuda_device(gpu_ids, visible_devices=visible, device_count=count)


@pytest.fixture
def fake_cuda(monkeypatch):
    """torch and Warp as a worker with ``count`` GPUs would see them: the current device set, described by UUID."""
    chosen = []
    state = {"count": 1}
    monkeypatch.setattr(torch.cuda, "device_count", lambda: state["count"])
    monkeypatch.setattr(gpus, "use_cuda_device", chosen.append)
    monkeypatch.setattr(gpus, "describe_cuda_device", lambda device: {
        "device": device, "name": "Fake GPU", "uuid": f"GPU-fake-{device[-1]}", "memory_gib": 1.0})
    return state, chosen


def test_a_task_placement_records_the_gpu_and_makes_it_current(fake_cuda):
    state, chosen = fake_cuda
    placement = runner.task_placement("cuda", [3], environ={"CUDA_VISIBLE_DEVICES": "3"})
    assert placement["device"] == "cuda:0" and chosen == ["cuda:0"] and placement["host"] == socket.gethostname()
    assert placement["gpu"] == {"device": "cuda:0", "name": "Fake GPU", "uuid": "GPU-fake-0", "memory_gib": 1.0,
                                "ray_gpu_ids": ["3"], "cuda_visible_devices": "3"}
    state["count"] = 4
    placement = runner.task_placement("cuda", ["2"], environ={"CUDA_VISIBLE_DEVICES": "0,1,2,3"})
    assert placement["device"] == "cuda:2" and chosen[-1] == "cuda:2" and placement["gpu"]["uuid"] == "GPU-fake-2"
    assert runner.task_placement("cpu", [], environ={}) == {"device": "cpu", "host": socket.gethostname(),
                                                           "gpu": None}


def test_the_subject_task_fits_on_its_placement_and_reports_the_gpu(fake_cuda, monkeypatch):
    class FakeRay:
        @staticmethod
        def get_gpu_ids():
            return ["1"]

    class Events(list):
        put = list.append

    calls = []
    monkeypatch.setattr(runner, "import_ray", lambda: FakeRay)
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "1")

    def fake_fit_subject(subject, output, *, report, kill_at_step, placement, **options):
        report("started", {"resume_step": 0})
        calls.append((options, placement))
        return {"status": "done"}

    monkeypatch.setattr(runner, "fit_subject", fake_fit_subject)
    events = Events()
    subject = runner.BatchSubject(name="alice", path=data.demo_subject_path())
    options = dict(config=None, device="cuda", preset_name="default", evaluate=False)
    assert runner._subject_task(events, subject, "out", options, None) == {"status": "done"}
    (fit_options, placement), = calls
    assert fit_options["device"] == "cuda:0" and placement["gpu"]["ray_gpu_ids"] == ["1"]
    assert events == [("alice", "started", {"resume_step": 0, "host": socket.gethostname(),
                                            "gpu_uuid": "GPU-fake-0"})]


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_torch_and_warp_name_the_same_gpu():
    described = gpus.describe_cuda_device("cuda:0")
    assert described["uuid"].startswith("GPU-") and described["memory_gib"] > 0
    listed = subprocess.run(["nvidia-smi", "-L"], capture_output=True, text=True).stdout
    assert described["uuid"] in listed, (described, listed)


_WAIT_FOR_TURN = """
import sys, time
from warpavatar.batch.gpus import compiled_marker_name, first_compile_turn
compiled_marker_name("cpu")  # the imports done
print("ready", flush=True)
start = time.time()
with first_compile_turn(sys.argv[1], "cpu"):
    print(f"{time.time() - start:.2f}", flush=True)
"""


def test_fits_with_a_cold_kernel_cache_take_turns_and_a_warm_one_does_not_wait(tmp_path):
    cache = tmp_path / "cache"
    with pytest.raises(RuntimeError):  # a turn that fails records nothing
        with first_compile_turn(cache, "cpu"):
            raise RuntimeError("compile failed")
    marker = cache / compiled_marker_name("cpu")
    assert not marker.exists()
    with first_compile_turn(cache, "cpu"):
        other = subprocess.Popen([sys.executable, "-c", _WAIT_FOR_TURN, str(cache)], stdout=subprocess.PIPE,
                                 text=True)
        assert other.stdout.readline() == "ready\n"
        time.sleep(1.0)
        assert other.poll() is None  # it waits for this turn
    waited = float(other.communicate(timeout=120)[0])
    assert other.returncode == 0 and waited >= 0.9 and marker.exists()
    start = time.time()
    with first_compile_turn(cache, "cpu"):  # warm: no lock taken
        assert time.time() - start < 1.0
    assert compiled_marker_name("cpu") != compiled_marker_name("sm_90")


def test_scaling_efficiency_compares_with_the_fewest_gpus_of_the_same_share():
    add_efficiency = load_tool("bench_fit_many").add_efficiency
    rows = [{"gpus": gpus, "gpus_per_fit": share, "wall_s": wall}
            for gpus, share, wall in ((1, 1.0, 400.0), (2, 1.0, 210.0), (4, 1.0, 125.0), (1, 0.5, 300.0))]
    add_efficiency(rows)
    assert [row["efficiency"] for row in rows] == [1.0, round(400 / 420, 3), 0.8, 1.0]
    assert [row["vs_one_fit_a_gpu"] for row in rows] == [1.0, 1.0, 1.0, round(400 / 300, 3)]


def test_the_benchmark_runs_a_batch_on_two_fit_slots_on_the_cpu(tmp_path, capsys):
    pytest.importorskip("ray")
    bench = load_tool("bench_fit_many")
    output = tmp_path / "bench"
    # a kernel cache of the fits' own (--kernel-cache reaches every worker): a copy of this process's cache, so
    # nothing compiles again, without the records of earlier compile turns
    cache = gpus.kernel_cache_dir()
    shutil.copytree(cache, tmp_path / "cache" / cache.name, ignore=shutil.ignore_patterns("warpavatar-compile*"))
    tiny = [*TINY_FIT, "--iterations", "10", "--checkpoint-every", "1000", "--kernel-cache", str(tmp_path / "cache")]
    status = bench.main(["--subjects", str(data.demo_subject_path()), "-o", str(output), "--fits", "2",
                         "--gpus", "2", "--device", "cpu", "--cpus-per-fit", "1", "--warm-up-steps", "0",
                         "--", *tiny])
    assert status == 0
    printed = capsys.readouterr().out
    assert "| gpus | gpus_per_fit | fits | done | wall_s | per_fit_s |" in printed, printed
    record = json.loads((output / bench.RESULT_NAME).read_text())
    assert record["device"] == "cpu" and record["fit_options"] == tiny
    (row,) = record["rows"]
    assert (row["gpus"], row["fits"], row["done"], row["efficiency"]) == (2, 2, 2, 1.0) and row["per_fit_s"] > 0
    assert sorted(fit["subject"] for fit in row["fit_results"]) == ["robot", "robot-2"]
    assert all(fit["device"] == "cpu" and fit["gpu"] is None for fit in row["fit_results"])
    done = json.loads((output / "runs" / "2slot" / "robot-2" / "fit-many.json").read_text())
    assert done["host"] == socket.gethostname() and done["gpu"] is None and done["steps"] == 10
    assert os.path.realpath(output / "subjects" / "robot-2") == os.path.realpath(data.demo_subject_path())
    # the fits' compile turn recorded the kernels as compiled in their cache
    assert list((tmp_path / "cache" / cache.name).glob("warpavatar-compiled-cpu-*"))
