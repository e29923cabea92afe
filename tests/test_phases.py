"""The seconds of a fit outside its training steps: the phases a fit logs, and the cheaper paths of its warm-up and
previews giving what the plain ones gave."""

import json
import time

import cv2
import numpy as np
import pytest
import torch

from warpavatar import data
from warpavatar._src.cuda_graph import adam_options
from warpavatar.fit import Trainer, preset
from warpavatar.fit.outputs import write_previews
from warpavatar.fit.phases import PhaseClock


def _small_config(**overrides):
    values = dict(iterations=12, image_scale=0.5, max_train_frames=6, init_points_per_bone=20,
                  init_carve_candidates=8000, init_carve_points=600, sh_degree=1, grid_cells=16, grid_min_cells=6,
                  field_hidden=16, field_layers=2, field_warmup_steps=5, field_warmup_batch=300,
                  gaussian_only_steps=6, densify_from=4, densify_every=4, densify_until=10, checkpoint_every=1000,
                  log_every=4, preview_frames=2)
    values.update(overrides)
    return preset("quick", **values)


@pytest.fixture(scope="module")
def demo_video():
    return data.load_video_folder(data.demo_subject_path() / "train", scale=0.5)


def test_phase_clock_adds_up_each_phase():
    clock = PhaseClock("cpu")
    for _ in range(2):
        with clock.phase("sleep"):
            time.sleep(0.02)
    with pytest.raises(RuntimeError), clock.phase("failed"):
        raise RuntimeError("a phase that raises is timed too")
    assert list(clock.seconds) == ["sleep", "failed"]
    assert 0.04 <= clock.seconds["sleep"] < 1.0
    rounded = clock.rounded()
    assert rounded["total"] == pytest.approx(sum(clock.seconds.values()), abs=2e-3)


def test_fit_logs_its_phases(demo_video, tmp_path):
    clock = PhaseClock("cpu")
    with clock.phase("load"):
        time.sleep(0.01)  # stands for reading the folder, timed by the caller on the same clock
    start = time.perf_counter()
    trainer = Trainer(demo_video, _small_config(), tmp_path / "fit", phases=clock)
    trainer.fit(progress=False)
    wall = time.perf_counter() - start
    log = [json.loads(line) for line in (tmp_path / "fit" / "train_log.jsonl").read_text().splitlines()]
    assert log[-1]["stage"] == "phases" and log[-1]["step"] == 12
    seconds = log[-1]["phase_seconds"]
    assert list(seconds) == ["load", "init", "warmup", "first_step", "steps", "extensions_finish", "avatar.pt",
                             "canonical.ply", "training_poses.npz", "extension_outputs", "checkpoint.pt",
                             "previews", "total"]
    assert all(value >= 0 for value in seconds.values())
    assert seconds["load"] >= 0.01 and seconds["steps"] > 0 and seconds["previews"] > 0
    # the phases cover the fit: their sum is its wall time, less the moments between them
    assert 0.9 * wall <= seconds["total"] - seconds["load"] <= wall + 1e-3
    # an interrupted fit logs its phases too, its last checkpoint as one
    stopped = Trainer(demo_video, _small_config(), tmp_path / "stopped")
    stopped.fit(progress=False, stop_at=5)
    last = json.loads((tmp_path / "stopped" / "train_log.jsonl").read_text().splitlines()[-1])
    assert last["step"] == 5 and "checkpoint.pt" in last["phase_seconds"] and "previews" not in last["phase_seconds"]


def test_warmup_draws_the_same_grid_points_as_one_draw_a_step(demo_video, tmp_path):
    """The warm-up copies its random grid points to the device 100 steps at a time; the field it trains is the one
    that one draw and one copy a step gave (across the boundary of two copies)."""
    steps = 103
    config = _small_config(field_warmup_steps=steps)
    stage = Trainer(demo_video, config, tmp_path / "fit").skinning
    field = stage.field
    start = {name: value.clone() for name, value in field.state_dict().items()}
    loss = stage.warmup(steps)
    trained = {name: value.clone() for name, value in field.state_dict().items()}

    field.load_state_dict(start)
    optimizer = torch.optim.Adam(field.parameters(), lr=config.field_lr, **adam_options(torch.device("cpu")))
    generator = torch.Generator().manual_seed(config.seed)
    for _ in range(steps):  # the warm-up as it was: a draw of field_warmup_batch points a step
        optimizer.zero_grad(set_to_none=True)
        chosen = torch.randint(field.cell_count, (config.field_warmup_batch,), generator=generator)
        reference_loss = field.distillation_loss(stage.prior, chosen)
        reference_loss.backward()
        optimizer.step()
    assert loss == float(reference_loss.detach())
    changed = 0
    for name, value in field.state_dict().items():
        assert torch.equal(value, trained[name]), name
        changed += not torch.equal(value, start[name])
    assert changed >= 4  # the MLP's layers trained


def test_previews_are_the_renders_of_their_frames(demo_video, tmp_path):
    """The previews evaluate the skinning grid once for all frames: each is the frame's own render, bit for bit."""
    trainer = Trainer(demo_video, _small_config(), tmp_path / "fit")
    trainer.fit(progress=False, stop_at=8)
    frames = trainer.frames
    write_previews(trainer.avatar, frames, tmp_path / "previews", count=3)
    indices = frames.spread(3)
    assert len(indices) == 3
    for index in indices:
        with torch.no_grad():
            image, _, _ = trainer.avatar.render(frames.cameras[index], frames.bone_transforms[index],
                                                background=frames.background)
        target, _ = frames.target(index)
        written = cv2.imread(str(tmp_path / "previews" / f"{frames.frame_id(index):06d}.png"))
        written = cv2.cvtColor(written, cv2.COLOR_BGR2RGB)
        expected = (torch.cat([image, target], dim=1).clamp(0, 1).numpy() * 255).round().astype(np.uint8)
        assert written.std() > 5  # a picture, not a blank
        assert np.array_equal(written, expected), index
