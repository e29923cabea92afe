"""The demo's preset and the CPU torch settings of ``warpavatar-fit`` (issue 18: the demo in 3 minutes on 2 cores)."""

import json

import pytest
import torch

from warpavatar.cli.common import cpu_torch_settings
from warpavatar.fit import Trainer, preset, preset_values
from warpavatar.fit.presets import CORE_PRESETS, PRESET_BASES

pytestmark = pytest.mark.torch_threads  # (these check the commands' own thread settings: torch's defaults here)


def test_demo_preset_is_quick_with_its_own_changes():
    quick, demo = preset_values("quick"), preset_values("demo")
    assert PRESET_BASES["demo"] == "quick"
    # every value the demo does not change is quick's, extensions' values included (pose correction off)
    for name, value in quick.items():
        assert demo[name] == CORE_PRESETS["demo"].get(name, value), name
    assert demo["pose_correction"] is False and demo["image_scale"] == 0.5
    assert demo["iterations"] < quick["iterations"] and demo["max_gaussians"] < quick["max_gaussians"]
    config = preset("demo")
    # the stages stay in order inside the shorter fit
    assert config.field_warmup_steps < config.iterations
    assert config.densify_from < config.densify_until < config.iterations
    assert config.gaussian_only_steps < config.iterations and config.sh_increase_every * config.sh_degree < \
        config.iterations
    assert not config.enabled("pose_correction")


def test_cpu_torch_settings_use_one_thread_and_restore_it(monkeypatch):
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    before = torch.get_num_threads()
    with cpu_torch_settings(torch.device("cpu")):
        assert torch.get_num_threads() == 1
        # denormals are flushed to zero inside
        assert float(torch.tensor(1e-39, dtype=torch.float32) * 1.0) == 0.0
    assert torch.get_num_threads() == before
    assert float(torch.tensor(1e-39, dtype=torch.float32) * 1.0) != 0.0
    monkeypatch.setenv("OMP_NUM_THREADS", "2")
    torch.set_num_threads(2)
    try:
        with cpu_torch_settings(torch.device("cpu")):
            assert torch.get_num_threads() == 2  # the user's choice stays
    finally:
        torch.set_num_threads(before)


def test_demo_command_fits_with_the_demo_preset_on_one_thread(tmp_path, monkeypatch):
    from warpavatar.cli.fit import main

    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    threads_seen = []
    train_step = Trainer.train_step

    def recording_step(self):
        threads_seen.append(torch.get_num_threads())
        return train_step(self)

    monkeypatch.setattr(Trainer, "train_step", recording_step)
    before = torch.get_num_threads()
    out = tmp_path / "demo"
    assert main(["--demo", "--device", "cpu", "-o", str(out), "--iterations", "3", "--field-warmup-steps", "2",
                 "--init-carve-candidates", "2000", "--no-progress", "--preview-frames", "1"]) == 0
    config = json.loads((out / "config.json").read_text())
    assert config["max_gaussians"] == CORE_PRESETS["demo"]["max_gaussians"]
    assert config["iterations"] == 3 and config["image_scale"] == 0.5
    assert threads_seen == [1, 1, 1] and torch.get_num_threads() == before
    results = json.loads((out / "demo_eval.json").read_text())
    assert set(results) == {"novel_view/cam_090", "novel_pose/dance_cam000"}
    assert all(result["psnr_masked"] > 5.0 for result in results.values())
