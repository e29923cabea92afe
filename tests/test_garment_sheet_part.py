"""The garment as a simulated sheet (``--garment-surface sheet``): detection and the sheet in a tiny fit, the fitted
per-frame states, their tracking to the masks and their physics residual, the avatar file, novel poses and new
motions; the node model stays the default."""

from __future__ import annotations

import io
import json
import math

import pytest
import torch

from warpavatar import data, ops
from warpavatar.extensions.garment import GarmentExtension, GarmentOptions
from warpavatar.extensions.garment_sheet_part import GarmentSheetPart, SheetFit
from warpavatar.fit import Trainer, preset
from warpavatar.model import Avatar

from tests.test_garment_capture import TINY

# a forced garment on the robot (every slightly split Gaussian, hung from the root) as a coarse sheet
SHEET = {**TINY, "iterations": 20, "garment_surface": "sheet", "garment_sheet_rings": 5, "garment_sheet_segments": 10,
         "garment_sheet_substep": 1.0 / 120.0, "garment_settle_substeps": 60, "garment_sheet_frames": 3,
         "checkpoint_every": 12, "garment_sheet_track_iterations": 8, "garment_sheet_track_every": 10,
         "garment_sheet_track_frames": 2}


@pytest.fixture(scope="module")
def video():
    return data.load_video_folder(data.demo_subject_path() / "train", max_frames=8, scale=0.5)


@pytest.fixture(scope="module")
def fitted(video, tmp_path_factory):
    folder = tmp_path_factory.mktemp("sheet")
    trainer = Trainer(video, preset("quick", **{**SHEET, "garment_attach": video.skeleton.names[0]}), folder)
    trainer.fit(progress=False)
    return trainer, folder


def _ring_distance(part: GarmentSheetPart, vertices: torch.Tensor) -> torch.Tensor:
    """Each vertex's distance [V] to the nearest ring vertex of the same sheet."""
    return torch.cdist(vertices, vertices[part.attached]).min(dim=1).values


def test_the_fit_builds_a_sheet_and_fits_every_frames_state(fitted):
    trainer, folder = fitted
    part = trainer.avatar.part("garment")
    assert isinstance(part, GarmentSheetPart)
    count = trainer.frames.count
    assert part.frame_states.shape == (count, part.node_count, 3) and part.attached.numel() > 0
    assert float(part.frame_states.detach()[:, part.attached].abs().max()) == 0.0  # the ring is the body's
    assert part.triangle_ids.shape == part.gaussian_ids.shape and int(part.gaussian_ids.max()) < trainer.gaussians.count
    report = json.loads((folder / "garment_sheet.json").read_text())
    assert report["vertices"] == part.node_count and report["training_frames"] == count
    assert report["image_steps_per_frame"]["mean"] > 0 and report["residual_steps"] > 0
    assert report["final_residual"] is not None and report["final_residual"] >= 0
    assert (folder / "garment_sheet.ply").stat().st_size > 0
    assert any('"garment_sheet"' in line and "final_residual" in line
               for line in trainer.log_path.read_text().splitlines())
    lines = trainer.extension("garment").summary_lines()
    assert any(line.startswith("garment sheet:") for line in lines)
    sheet = trainer.extension("garment").sheet
    # tracked to the masks right after the rollout (step 4) and once more (--garment-sheet-track-every 10)
    assert [record["step"] for record in report["tracking"]] == [4, 14] == [r["step"] for r in sheet.tracking]
    for record in report["tracking"]:
        assert record["iterations"] == 8 and record["frames"] == count
        assert len(record["coverage_iou"]["after"]["per_frame"]) == count
        for name in ("outside", "uncovered", "dynamics", "edges"):
            assert record[name]["before"] >= 0 and record[name]["after"] >= 0
    assert 0.0 <= report["final_silhouette"]["coverage_iou"]["mean"] <= 1.0
    assert any(line.startswith("garment sheet tracking: 2 run(s)") for line in lines)
    assert any(line.startswith("garment sheet at the end:") for line in lines)
    assert any('"garment_sheet_tracking"' in line for line in trainer.log_path.read_text().splitlines())
    assert sheet.states_optimizer.state[part.frame_states]["exp_avg"].abs().sum() > 0  # the images moved them
    # the table of the training instants holds the fitted states
    bones = sheet.bones
    torch.testing.assert_close(part.frame_vertices, part.state_vertices(bones, part.frame_states.detach()))


def test_posed_at_the_rest_sheet_the_gaussians_are_where_they_are(fitted):
    trainer, _ = fitted
    part = trainer.avatar.part("garment")
    gaussians = trainer.gaussians
    ids = part.gaussian_ids
    with torch.no_grad():
        local = part.local_values(gaussians.means[ids], gaussians.normalized_quats[ids], gaussians.scales[ids])
        means, quats, log_scales = ops.pose_triangle_gaussians(part.rest_vertices, part.faces, part.rest_area,
                                                               part.triangle_ids, *local)
    torch.testing.assert_close(means, gaussians.means[ids].detach(), atol=1e-4, rtol=0)
    sign = torch.sign((quats * gaussians.normalized_quats[ids]).sum(1, keepdim=True))
    torch.testing.assert_close(quats * sign, gaussians.normalized_quats[ids].detach(), atol=1e-4, rtol=0)
    torch.testing.assert_close(log_scales.exp(), gaussians.scales[ids].detach(), rtol=1e-4, atol=1e-7)


def test_the_states_residual_falls_as_the_states_and_the_physics_fit_it(fitted):
    trainer, _ = fitted
    sheet = trainer.extension("garment").sheet
    part = sheet.part
    saved = part.frame_states.detach().clone()
    try:
        with torch.no_grad():
            generator = torch.Generator().manual_seed(0)
            part.frame_states.add_(0.05 * part.edge_length * torch.randn(saved.shape, generator=generator)
                                   * part.free_mask)
        before = sheet.whole_residual()
        for step in range(12):
            for optimizer in sheet.optimizers():
                optimizer.zero_grad(set_to_none=True)
            sheet._residual(sheet._batch(step)).backward()
            for optimizer in sheet.optimizers():
                optimizer.step()
        after = sheet.whole_residual()
        assert after < 0.7 * before, (before, after)
    finally:
        with torch.no_grad():
            part.frame_states.copy_(saved)


def test_the_sheet_part_round_trips_and_poses_new_motions(fitted, video, tmp_path):
    trainer, _ = fitted
    loaded = Avatar.load(trainer.avatar.save(tmp_path / "avatar.pt"))
    part = loaded.part("garment")
    assert isinstance(part, GarmentSheetPart)
    camera = video.cameras[0]
    rest_reach = float(_ring_distance(part, part.rest_vertices).max())
    motion = torch.as_tensor(video.bone_transforms[:6], dtype=torch.float32).flip(0).contiguous()
    with torch.no_grad():
        pose = trainer.frames.bone_transforms[3]  # a training instant: its fitted state, the same after loading
        assert torch.equal(trainer.avatar.render(camera, pose)[0], loaded.render(camera, pose)[0])
        loaded.prepare_sequence(motion)
        for index in (0, 5):
            image = loaded.render(camera, motion[index])[0]
            assert torch.isfinite(image).all()
        reach = _ring_distance(part, part._sequence[1][-1])
        assert torch.isfinite(part._sequence[1]).all() and float(reach.max()) <= 1.25 * rest_reach
        lone = trainer.frames.bone_transforms[2].clone()
        lone[:, 2, 3] += 0.05  # a pose of no sequence: the sheet settles there
        image = loaded.render(camera, lone)[0]
        assert torch.isfinite(image).all() and float(_ring_distance(part, part._lone[1]).max()) <= 1.25 * rest_reach


def test_the_image_loss_reaches_the_states_and_the_garment_gaussians(fitted):
    trainer, _ = fitted
    part = trainer.avatar.part("garment")
    sheet = trainer.extension("garment").sheet
    index = 3
    vertices = part.state_vertices(sheet.bones[index:index + 1], part.frame_states[index:index + 1])[0]
    image = trainer.avatar.render(trainer.frames.cameras[index], trainer.frames.bone_transforms[index],
                                  inputs={"garment": vertices})[0]
    states, means = torch.autograd.grad(image.square().sum(), [part.frame_states, trainer.gaussians.means])
    assert float(states[index].abs().sum()) > 0 and float(states[:index].abs().sum()) == 0
    assert float(states[index][part.attached].abs().max()) == 0.0
    assert float(means[part.gaussian_ids].abs().sum()) > 0


def test_a_step_that_breaks_a_frames_sheet_is_undone(fitted):
    trainer, _ = fitted
    sheet = trainer.extension("garment").sheet
    part, states = sheet.part, sheet.part.frame_states
    saved = states.detach().clone()
    with torch.no_grad():
        states[1:3] = 0.0  # the skinned rest sheet: a valid sheet
    before = states.detach().clone()
    moments = sheet.states_optimizer.state[states]
    saved_moments = {name: moments[name].clone() for name in ("exp_avg", "exp_avg_sq")}
    counts = int(sheet.reverted_states), int(sheet.non_finite_steps)
    assert bool(sheet.tracker().valid_frames(before)[1:3].all())
    try:
        states.grad = torch.zeros_like(states)
        states.grad[0, 0, 0] = math.nan
        sheet.after_backward(None)
        assert bool(torch.isfinite(states.grad).all()) and int(sheet.non_finite_steps) == counts[1] + 1
        with torch.no_grad():  # "the step": frame 1's free vertices squashed to one point, frame 2 nudged
            skinned = sheet.skinned[1]
            states[1] = (skinned[part.attached].mean(dim=0) - skinned) * part.free_mask
            states[2] += 1e-4 * part.free_mask
        sheet.after_step(None)
        assert torch.equal(states[1], before[1]) and not torch.equal(states[2], before[2])
        assert float(moments["exp_avg"][1].abs().max()) == 0.0 and torch.equal(moments["exp_avg"][2],
                                                                                saved_moments["exp_avg"][2])
        assert int(sheet.reverted_states) == counts[0] + 1
        sheet.after_backward(None)  # no gradient of the states: nothing non-finite, nothing reverted
        sheet.after_step(None)
        assert (int(sheet.reverted_states), int(sheet.non_finite_steps)) == (counts[0] + 1, counts[1] + 1)
    finally:
        with torch.no_grad():
            states.copy_(saved)
            for name, value in saved_moments.items():
                moments[name].copy_(value)
        states.grad = None
        sheet.reverted_states.fill_(counts[0])
        sheet.non_finite_steps.fill_(counts[1])


def test_resume_gives_the_same_states_bit_for_bit(fitted, video, tmp_path):
    whole, _ = fitted
    config = preset("quick", **{**SHEET, "garment_attach": video.skeleton.names[0]})
    Trainer(video, config, tmp_path).fit(progress=False, stop_at=14)
    resumed = Trainer(video, config, tmp_path)
    resumed.fit(resume=True, progress=False)
    assert torch.equal(whole.avatar.part("garment").frame_states, resumed.avatar.part("garment").frame_states)
    assert torch.equal(whole.gaussians.means, resumed.gaussians.means)
    # the tracking runs (one before the checkpoint, one after) came at the same steps to the same values
    runs = [[{k: v for k, v in record.items() if k != "seconds"} for record in trainer.extension("garment").sheet
             .tracking] for trainer in (whole, resumed)]
    assert runs[0] == runs[1] and len(runs[0]) == 2


def test_the_sheet_fit_state_round_trips(fitted):
    trainer, _ = fitted
    extension = trainer.extension("garment")
    sheet, part = extension.sheet, extension.sheet.part
    state = torch.load(io.BytesIO(_saved(sheet.state_dict())), weights_only=True)
    try:
        loaded = SheetFit.from_state(extension, state)
        assert loaded.tracking == sheet.tracking and loaded.tracked == sheet.tracked == 14
        assert loaded.refreshed == sheet.refreshed and loaded.image_steps == sheet.image_steps
        assert torch.equal(loaded.part.frame_states, part.frame_states)
    finally:
        trainer.avatar.add_part(part)  # (the fixture's part back in the avatar)


def _saved(state: dict) -> bytes:
    buffer = io.BytesIO()
    torch.save(state, buffer)
    return buffer.getvalue()


def test_nodes_stay_the_default_and_the_sheet_options_are_checked():
    assert GarmentOptions().garment_surface == "nodes"
    for name, value in (("garment_surface", "mesh"), ("garment_sheet_rings", 1), ("garment_sheet_substep", 0.0),
                        ("lambda_garment_sheet_dynamics", -1.0), ("garment_settle_substeps", 0),
                        ("garment_sheet_track_iterations", -1), ("garment_sheet_track_every", -1),
                        ("garment_sheet_track_frames", -1), ("lr_garment_sheet_track", 0.0),
                        ("lambda_garment_sheet_track_dynamics", -0.1), ("lambda_garment_sheet_track_edges", math.inf),
                        ("garment_sheet_track_region", "mask")):
        with pytest.raises(ValueError, match=name.replace("_", "-")):
            GarmentExtension.check(GarmentOptions(**{name: value}), None)
