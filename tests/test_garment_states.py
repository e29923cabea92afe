"""The training frames' fitted cloth states (``--garment-frame-states on``): the dynamics residual that holds them
to the simulation, against a host-indexed reference; where they are used (the training instants) and where not
(any other pose); a steady step's device work; options (issue #17)."""

from __future__ import annotations

import pytest
import torch

from warpavatar import data
from warpavatar.extensions import StepContext
from warpavatar.extensions.garment import GarmentExtension, GarmentOptions
from warpavatar.fit import Trainer, preset
from warpavatar.sim import ClothState

from conftest import load_tool
from tests.test_garment_capture import TINY, _Uploads

STATES = {**TINY, "garment_frame_states": "on"}


@pytest.fixture(scope="module")
def video():
    return data.load_video_folder(data.demo_subject_path() / "train", max_frames=8, scale=0.5)


def _after_detection(video, folder, **overrides) -> Trainer:
    config = preset("quick", **{**STATES, "garment_attach": video.skeleton.names[0], **overrides})
    trainer = Trainer(video, config, folder)
    while trainer.avatar.part("garment") is None:
        trainer.train_step()
    return trainer


def _host_residual(extension, states, index: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The reference: frame ``index`` drawn at ``skinned_i(P) + y_i``; the frames after ``s = max(0, i - W)`` up to
    ``i`` simulated with host indices from ``x_s`` moving at ``(x_s - x_{s-1}) / dt`` (the rollout's frame-0
    velocity at ``s = 0``), each one's mean squared distance to its fitted positions over the free nodes, over the
    node spacing squared, averaged over the W slots (a slot before frame 1 adds nothing)."""
    part, bones, seconds = extension.part, extension.bones, extension.fit.frames.seconds
    window = extension.options.garment_window
    free = part.free_mask[:, 0] > 0
    fitted = [part.skinned_rest(bones[k]) + states[k] * part.free_mask for k in range(bones.shape[0])]
    start = max(0, index - window)
    velocity = (fitted[start] - fitted[start - 1]) / seconds[start] if start >= 1 else extension.cache[1][0]
    state = ClothState(fitted[start], velocity)
    residual = fitted[0].new_zeros(())
    for frame in range(start + 1, index + 1):
        state = part.step(state, bones[frame - 1], bones[frame], seconds[frame])
        residual = residual + ((state.positions - fitted[frame])[free] ** 2).sum(-1).mean()
    return fitted[index], residual / (window * part.hyper["voxel_size"] ** 2)


@pytest.mark.parametrize("max_train_frames", [8, 6])  # evenly timed (the captured case), and not
def test_the_device_window_matches_the_host_reference(video, tmp_path, max_train_frames):
    """Drawn positions, residual and the gradients of both (to the states, the physics and the rest shape), for
    every training frame, equal the host-indexed reference's; the frames outside a window get no gradient."""
    trainer = _after_detection(video, tmp_path, max_train_frames=max_train_frames)
    extension = trainer.extension("garment")
    part = extension.part
    assert extension.fits_states and part.frame_states.shape == (trainer.frames.count, part.node_count, 3)
    generator = torch.Generator().manual_seed(3)
    with torch.no_grad():  # states and a rest shape away from the rollout's, so every term is exercised
        part.frame_states.add_(0.02 * torch.randn(part.frame_states.shape, generator=generator))
        part.cloth.rest_offset_logit.copy_(0.5 * torch.randn(part.cloth.rest_offset_logit.shape, generator=generator))
    parameters = [part.frame_states, *part.cloth.parameters()]
    window = extension.options.garment_window
    for index in range(trainer.frames.count):
        step = StepContext(step=trainer.step, index=index, train_field=True, frame=torch.tensor(index))
        extension.frame_input(step)
        ours = extension.step_input(step)
        assert bool(extension.skip_update) == (index == 0)
        theirs, their_residual = _host_residual(extension, part.frame_states, index)
        torch.testing.assert_close(ours, theirs, rtol=0, atol=1e-6)
        torch.testing.assert_close(extension.residual, their_residual, rtol=1e-5, atol=1e-9)
        assert (float(extension.residual.detach()) > 0) == (index > 0)
        cotangent = torch.randn(ours.shape, generator=generator)
        ours_grads, their_grads = (
            [torch.zeros_like(p) if g is None else g for p, g in
             zip(parameters, torch.autograd.grad((drawn * cotangent).sum() + residual, parameters, allow_unused=True))]
            for drawn, residual in ((ours, extension.residual), (theirs, their_residual)))
        for a, b in zip(ours_grads, their_grads):
            torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-7)
        touched = ours_grads[0].abs().sum(dim=(1, 2)) > 0
        first = max(0, index - window - 1)
        assert not touched[:first].any() and not touched[index + 1:].any()  # only the window's frames
        assert touched[index]
        assert float(ours_grads[0][:, part.attached].abs().max()) == 0.0  # the body holds the attached nodes


def test_states_are_drawn_on_their_instants_only(video, tmp_path):
    """After training: the states moved, attached nodes never; a training instant is drawn from its state (the
    refreshed table), while a new motion's cloth is the simulation's whatever the states are."""
    trainer = _after_detection(video, tmp_path)
    extension = trainer.extension("garment")
    part = extension.part
    start = part.frame_states.detach().clone()
    for _ in range(10):
        trainer.train_step()
    assert not torch.equal(start, part.frame_states)
    assert float(part.frame_states.detach()[:, part.attached].abs().max()) == 0.0
    extension.refresh()
    bones = extension.bones
    torch.testing.assert_close(part.frame_positions, part.state_positions(bones, part.frame_states.detach()))
    motion = torch.as_tensor(video.bone_transforms[:5], dtype=torch.float32).flip(0).contiguous()
    with torch.no_grad():
        trainer.avatar.prepare_sequence(motion)
        before = trainer.avatar.part("garment")._sequence[1].clone()
        part.frame_states.add_(0.1)
        extension.refresh()
        trainer.avatar.prepare_sequence(motion)
    assert torch.equal(before, part._sequence[1])  # novel poses: the physics alone
    camera = video.cameras[2]
    pose = trainer.frames.bone_transforms[2]
    with torch.no_grad():
        moved = trainer.avatar.render(camera, pose)[0]
        part.frame_states.sub_(0.1)
        extension.refresh()
        back = trainer.avatar.render(camera, pose)[0]
    assert not torch.equal(moved, back)  # the training instant: its fitted state


def test_states_off_fits_the_simulation_alone(video, tmp_path):
    trainer = _after_detection(video, tmp_path, garment_frame_states="off")
    _, terms = trainer.train_step()
    assert trainer.avatar.part("garment").frame_states.shape[0] == 0
    assert "garment_dynamics" not in terms and "garment_stretch" not in terms
    assert trainer.extension("garment").states_optimizer is None


def test_the_states_losses_are_reported_and_trained(video, tmp_path):
    trainer = _after_detection(video, tmp_path)
    seen = []
    for _ in range(6):
        _, terms = trainer.train_step()
        seen.append({name: float(terms[name].value) for name in ("garment_dynamics", "garment_stretch")})
    assert all(value["garment_stretch"] > 0 for value in seen)
    assert any(value["garment_dynamics"] > 0 for value in seen)
    optimizer = trainer.extension("garment").states_optimizer
    assert optimizer.state[trainer.avatar.part("garment").frame_states]["exp_avg"].abs().sum() > 0


def test_a_steady_states_step_reads_nothing_from_the_device(video, tmp_path):
    trainer = _after_detection(video, tmp_path, garment_refresh_every=1000)
    for _ in range(3):
        trainer.train_step()
    trainer.step = 24
    extension = trainer.extension("garment")
    assert extension.step_capturable(None) and extension.fits_states
    states = extension.part.frame_states.detach().clone()
    uploads = _Uploads()
    with uploads:
        counts = load_tool("bench_avatar").count_step_work(trainer.train_step, device="cpu", steps=2)
    assert counts["host_reads"] == 0, counts
    assert uploads.places == [], uploads.places
    assert not torch.equal(states, extension.part.frame_states)


@pytest.mark.parametrize("name, value", [("garment_frame_states", "sometimes"), ("lr_garment_states", 0.0),
                                         ("lambda_garment_dynamics", -1.0), ("lambda_garment_stretch", float("nan"))])
def test_bad_state_options_are_rejected(name, value):
    with pytest.raises(ValueError, match=name.replace("_", "-")):
        GarmentExtension.check(GarmentOptions(**{name: value}), None)


def test_resume_gives_the_same_states_bit_for_bit(video, tmp_path):
    config = preset("quick", **{**STATES, "garment_attach": video.skeleton.names[0], "iterations": 24,
                                "checkpoint_every": 16})
    whole = Trainer(video, config, tmp_path / "whole")
    whole.fit(progress=False)
    Trainer(video, config, tmp_path / "parts").fit(progress=False, stop_at=18)
    resumed = Trainer(video, config, tmp_path / "parts")
    resumed.fit(resume=True, progress=False)
    states = whole.avatar.part("garment").frame_states
    assert states.shape[0] == whole.frames.count and states.abs().sum() > 0
    assert torch.equal(states, resumed.avatar.part("garment").frame_states)
    assert torch.equal(whole.gaussians.means, resumed.gaussians.means)


def test_training_flows_follow_a_shifted_texture():
    """Frame 1 is frame 0 moved by (+6, +4) px: the forward flow of frame 0 and the backward flow of frame 1
    carry the textured middle by that and its opposite (in full-frame pixels, at the stored resolution); the flows
    out of the sequence are zero."""
    from warpavatar.extensions.garment import training_flows

    generator = torch.Generator().manual_seed(0)
    texture = torch.nn.functional.interpolate(torch.rand(1, 3, 40, 40, generator=generator), size=(240, 240),
                                              mode="bilinear", align_corners=False)[0].permute(1, 2, 0)
    base = (texture * 255).to(torch.uint8).numpy()
    frames = torch.zeros(2, 200, 200, 3, dtype=torch.uint8).numpy()
    frames[0] = base[20:220, 20:220]
    frames[1] = base[16:216, 14:214]  # content moves right by 6 and down by 4
    forward, backward = training_flows(frames)
    assert forward.shape == backward.shape == (2, 192, 192, 2) and forward.dtype == torch.float16
    middle = slice(48, 144)
    torch.testing.assert_close(forward[0, middle, middle].float().mean((0, 1)), torch.tensor([6.0, 4.0]), atol=0.5,
                               rtol=0)
    torch.testing.assert_close(backward[1, middle, middle].float().mean((0, 1)), torch.tensor([-6.0, -4.0]),
                               atol=0.5, rtol=0)
    assert forward[1].abs().max() == 0 and backward[0].abs().max() == 0
