"""The seconds of a fit outside its training steps: the phases a fit logs, and the cheaper paths of its warm-up and
previews giving what the plain ones gave."""

import copy
import json
import math
import time

import cv2
import numpy as np
import pytest
import torch

from warpavatar import data
from warpavatar._src.cuda_graph import adam_options
from warpavatar.fit import Trainer, preset
from warpavatar.fit.checkpoint import CHECKPOINT_FORMAT, CheckpointWriter
from warpavatar.fit.outputs import write_previews
from warpavatar.fit.phases import PhaseClock
from warpavatar.geometry import quat_to_matrix
from warpavatar.model import GaussianModel
from warpavatar.model.gaussians import _PARAMETER_NAMES


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


def test_phase_clock_stops_the_outer_phase_while_an_inner_one_runs():
    clock = PhaseClock("cpu")
    start = time.perf_counter()
    with clock.phase("outer"):
        time.sleep(0.02)
        for _ in range(2):
            with clock.phase("inner"):
                time.sleep(0.05)
        time.sleep(0.02)
    wall = time.perf_counter() - start
    assert 0.1 <= clock.seconds["inner"] < 0.1 + 0.05
    assert 0.04 <= clock.seconds["outer"] < 0.04 + 0.05  # without the inner phases' 0.1 s
    assert clock.seconds["inner"] + clock.seconds["outer"] == pytest.approx(wall, abs=5e-3)


def test_fit_logs_its_phases(demo_video, tmp_path):
    clock = PhaseClock("cpu")
    with clock.phase("load"):
        time.sleep(0.01)  # stands for reading the folder, timed by the caller on the same clock
    start = time.perf_counter()
    trainer = Trainer(demo_video, _small_config(checkpoint_every=5), tmp_path / "fit", phases=clock)
    trainer.fit(progress=False)
    wall = time.perf_counter() - start
    log = [json.loads(line) for line in (tmp_path / "fit" / "train_log.jsonl").read_text().splitlines()]
    assert log[-1]["stage"] == "phases" and log[-1]["steps_done"] == 12 and "step" not in log[-1]
    seconds = log[-1]["phase_seconds"]
    assert list(seconds) == ["load", "init", "warmup", "first_step", "steps", "densify", "checkpoints",
                             "extensions_finish", "avatar.pt", "canonical.ply", "training_poses.npz",
                             "extension_outputs", "checkpoint.pt", "previews", "total"]
    assert all(value >= 0 for value in seconds.values())
    assert seconds["load"] >= 0.01 and seconds["steps"] > 0 and seconds["previews"] > 0
    assert seconds["densify"] > 0 and seconds["checkpoints"] > 0  # rounds after steps 4 and 8, saves at 5 and 10
    # the phases cover the fit: their sum is its wall time, less the moments between them
    assert 0.9 * wall <= seconds["total"] - seconds["load"] <= wall + 1e-3
    # an interrupted fit logs its phases too, its last checkpoint as one
    stopped = Trainer(demo_video, _small_config(), tmp_path / "stopped")
    stopped.fit(progress=False, stop_at=5)
    last = json.loads((tmp_path / "stopped" / "train_log.jsonl").read_text().splitlines()[-1])
    assert last["steps_done"] == 5
    assert "checkpoint.pt" in last["phase_seconds"] and "previews" not in last["phase_seconds"]


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


def _gaussians_with_moments(count: int, seed: int) -> GaussianModel:
    """Random Gaussians whose Adam moments are not zero (two steps on random gradients)."""
    generator = torch.Generator().manual_seed(seed)
    gaussians = GaussianModel(torch.randn(count, 3, generator=generator),
                              torch.rand(count, 3, generator=generator),
                              0.02 + 0.1 * torch.rand(count, 3, generator=generator), sh_degree=1)
    with torch.no_grad():
        gaussians.quats.copy_(torch.randn(count, 4, generator=generator))
        gaussians.opacity_logits.copy_(torch.randn(count, generator=generator).reshape(gaussians.opacity_logits.shape))
    gaussians.make_optimizer(lr_position=1e-3, lr_scale=1e-2, lr_rotation=1e-3, lr_opacity=1e-2, lr_color=1e-2)
    for _ in range(2):
        for parameter in gaussians.parameters():
            parameter.grad = torch.randn(parameter.shape, generator=generator)
        gaussians.optimizer.step()
    return gaussians


def _state(gaussians: GaussianModel) -> dict[str, torch.Tensor]:
    values = {name: getattr(gaussians, name).detach().clone() for name in _PARAMETER_NAMES}
    for name in _PARAMETER_NAMES:
        moments = gaussians.optimizer.state[getattr(gaussians, name)]
        values.update({f"{name}.{key}": moments[key].clone() for key in ("exp_avg", "exp_avg_sq")})
    return values


def _assert_same(state: dict, expected: dict) -> None:
    assert state.keys() == expected.keys()
    for name, value in expected.items():
        assert torch.equal(state[name], value), name


def test_densify_and_prune_rebuild_what_append_then_masked_prune_built():
    """Densification rebuilds the parameters and moments once (the split Gaussians dropped as their samples are
    added) and pruning gathers by an index read once: the same Gaussians, moments and renumbering as appending,
    then masking, gave."""
    count, threshold, size_split = 400, 0.5, 0.07
    gaussians, reference = _gaussians_with_moments(count, 5), _gaussians_with_moments(count, 5)
    grad_norm = torch.rand(count, generator=torch.Generator().manual_seed(6))
    source = gaussians.densify(grad_norm, threshold=threshold, size_split=size_split,
                               generator=torch.Generator().manual_seed(7))

    # the reference: densification as it was written before (append everything, then mask the split ones out)
    selected = grad_norm >= threshold
    max_scale = reference.scales.detach().max(dim=1).values
    clone_index = torch.nonzero(selected & (max_scale <= size_split)).squeeze(1)
    split_index = torch.nonzero(selected & (max_scale > size_split)).squeeze(1)
    assert clone_index.numel() > 10 and split_index.numel() > 10  # both kinds happen
    split = reference.raw_parameters(split_index)
    generator = torch.Generator().manual_seed(7)
    stds = split["log_scales"].exp()
    rotations = quat_to_matrix(split["quats"] / split["quats"].norm(dim=-1, keepdim=True))
    samples = [split["means"] + torch.einsum("nij,nj->ni", rotations, torch.randn(stds.shape, generator=generator)
                                             * stds) for _ in range(2)]
    two = {name: torch.cat([value, value]) for name, value in split.items()}
    two.update(means=torch.cat(samples), log_scales=two["log_scales"] - math.log(1.6))
    clones = reference.raw_parameters(clone_index)
    reference.append({name: torch.cat([clones[name], two[name]]) for name in _PARAMETER_NAMES})
    keep = torch.ones(reference.count, dtype=torch.bool)
    keep[split_index] = False
    state = _state(reference)
    reference_source = torch.cat([torch.arange(count), clone_index, split_index, split_index])[keep]
    _assert_same(_state(gaussians), {name: value[keep] for name, value in state.items()})
    assert torch.equal(source, reference_source)

    # pruning by a mask and by its indices: the masked rows of every parameter and moment
    keep = gaussians.opacities.detach() > 0.4
    assert 0 < int(keep.sum()) < gaussians.count
    expected = {name: value[keep] for name, value in _state(gaussians).items()}
    other = _gaussians_with_moments(count, 5)
    other.densify(grad_norm, threshold=threshold, size_split=size_split, generator=torch.Generator().manual_seed(7))
    gaussians.prune(keep)
    other.prune(torch.nonzero(keep).squeeze(1))
    _assert_same(_state(gaussians), expected)
    _assert_same(_state(other), expected)


def test_densify_without_splits_appends_the_clones():
    gaussians = _gaussians_with_moments(50, 8)
    before = _state(gaussians)
    grad_norm = torch.zeros(50)
    grad_norm[[3, 17, 40]] = 1.0
    source = gaussians.densify(grad_norm, threshold=0.5, size_split=10.0, generator=torch.Generator())
    assert torch.equal(source, torch.cat([torch.arange(50), torch.tensor([3, 17, 40])]))
    after = _state(gaussians)
    for name, value in before.items():
        added = torch.zeros_like(value[[3, 17, 40]]) if "." in name else value[[3, 17, 40]]
        assert torch.equal(after[name], torch.cat([value, added])), name


def test_log_record_reads_every_term_as_its_own_read_gave(demo_video, tmp_path):
    trainer = Trainer(demo_video, _small_config(), tmp_path / "fit")
    trainer.fit(progress=False, stop_at=7)  # the field trains from step 6: its bone term is in the record
    step, terms = trainer.train_step()
    record = trainer._log_record(step, terms)
    assert {"loss", "l1", "bone"} <= set(terms)
    for name, term in terms.items():
        assert record[name] == float(term.value), name
    assert record["loss"] > 0 and record["gaussians"] == trainer.gaussians.count


def _assert_same_tree(value, expected, where="state"):
    assert type(value) is type(expected), where
    if isinstance(expected, torch.Tensor):
        assert value.device.type == "cpu" and torch.equal(value, expected), where
    elif isinstance(expected, dict):
        assert value.keys() == expected.keys(), where
        assert getattr(value, "_metadata", None) == getattr(expected, "_metadata", None), where
        for key in expected:
            _assert_same_tree(value[key], expected[key], f"{where}[{key!r}]")
    elif isinstance(expected, (list, tuple)):
        assert len(value) == len(expected), where
        for index, (item, expected_item) in enumerate(zip(value, expected)):
            _assert_same_tree(item, expected_item, f"{where}[{index}]")
    else:
        assert value == expected, where


def test_background_checkpoint_holds_the_state_when_it_was_saved(demo_video, tmp_path):
    """A checkpoint written while training goes on is the state of its step, not of a later one."""
    trainer = Trainer(demo_video, _small_config(iterations=20), tmp_path / "fit")
    trainer.fit(progress=False, stop_at=5)
    expected = copy.deepcopy(trainer.checkpoint_state())
    path = trainer.save_checkpoint(background=True)
    for _ in range(4):  # moves the Gaussians and a densification round renumbers them, while the file is written
        trainer.train_step()
    trainer._checkpoints.wait()
    saved = torch.load(path, map_location="cpu", weights_only=False)
    assert saved.pop("format") == CHECKPOINT_FORMAT and saved["step"] == 5
    _assert_same_tree(saved, expected)
    assert not torch.equal(saved["gaussians"]["means"], trainer.gaussians.means.detach()[:saved["gaussians"]["means"]
                                                                                       .shape[0]])
    # a fit resumed from it goes on as the one that wrote it
    resumed = Trainer(demo_video, _small_config(iterations=20), tmp_path / "fit")
    resumed.load_checkpoint(path)
    assert resumed.step == 5 and resumed.gaussians.count == saved["gaussians"]["means"].shape[0]


def test_failed_background_checkpoint_raises_at_the_next_save(tmp_path):
    writer = CheckpointWriter()
    writer.save(tmp_path / "missing" / "checkpoint.pt", {"step": 1, "values": torch.arange(3.0)})
    with pytest.raises(RuntimeError, match="does not exist"):  # torch's error for a missing folder
        writer.wait()
    writer.save(tmp_path / "checkpoint.pt", {"step": 2, "values": torch.arange(3.0)}, wait=True)
    assert torch.load(tmp_path / "checkpoint.pt", weights_only=False)["step"] == 2
