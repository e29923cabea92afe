"""The garment's training step as device work: a window of fixed length driven by the frame index on the device
(capturable as a CUDA graph), against the host-indexed eager window it replaces."""

from __future__ import annotations

import copy
import traceback

import pytest
import torch
from torch.utils._python_dispatch import TorchDispatchMode

from warpavatar import data
from warpavatar.extensions import StepContext
from warpavatar.fit import Trainer, preset
from warpavatar.sim import ClothState

from conftest import load_tool
from tests.test_garment_rest import host_window

# a forced garment on the robot (every slightly split Gaussian, hung from the root), coarse nodes and substeps;
# 8 training frames of the 8 loaded: evenly timed, so every window has the same frame length
TINY = dict(iterations=40, image_scale=0.5, max_train_frames=8, init_points_per_bone=20, init_carve_candidates=8000,
            init_carve_points=600, sh_degree=1, grid_cells=12, grid_min_cells=4, field_hidden=16, field_layers=1,
            field_warmup_steps=6, gaussian_only_steps=6, densify_from=8, densify_every=8, densify_until=20,
            checkpoint_every=1000, log_every=1000, preview_frames=0, garment="auto", garment_from=4,
            garment_threshold=0.0005, garment_min_fraction=0.01, garment_voxel=0.12, garment_substep=1.0 / 60.0,
            garment_window=3, garment_refresh_every=5, garment_frame_states="off")


@pytest.fixture(scope="module")
def video():
    return data.load_video_folder(data.demo_subject_path() / "train", max_frames=8, scale=0.5)


def _trainer(video, folder, **overrides):
    config = preset("quick", **{**TINY, "garment_attach": video.skeleton.names[0], **overrides})
    return Trainer(video, config, folder)


def _old_window(extension, index: int) -> torch.Tensor:
    """The eager window this module replaces (``host_window``): frames ``max(0, i - W) + 1 .. i`` stepped with
    host indices from the skinned rest shape plus the cached displacement, each frame's displacement and velocity
    written back into the cache."""
    return host_window(extension.part, extension.cache, extension.bones, extension.fit.frames.seconds, index,
                                 extension.options.garment_window).positions


def _after_detection(video, folder, **overrides) -> Trainer:
    trainer = _trainer(video, folder, **overrides)
    while trainer.avatar.part("garment") is None:
        trainer.train_step()
    return trainer


@pytest.mark.parametrize("max_train_frames", [8, 6])  # evenly timed (the captured case), and not
def test_the_device_window_is_the_eager_window(video, tmp_path, max_train_frames):
    """Node positions, the cloth's gradients and the cache the window leaves, for every training frame (the first
    ones, i < W, simulate only the frames after frame 0), equal those of the host-indexed window."""
    trainer = _after_detection(video, tmp_path, max_train_frames=max_train_frames)
    extension = trainer.extension("garment")
    assert extension.step_capturable(None) == (max_train_frames == 8)
    cloth = extension.part.cloth
    generator = torch.Generator().manual_seed(5)
    with torch.no_grad():  # a learned rest shape, which moves every window's start (the cache: displacements)
        cloth.rest_offset_logit.copy_(0.5 * torch.randn(cloth.rest_offset_logit.shape, generator=generator))
    names, parameters = zip(*cloth.named_parameters())
    assert "rest_offset_logit" in names
    for index in range(trainer.frames.count):
        step = StepContext(step=trainer.step, index=index, train_field=True,
                           frame=torch.tensor(index, dtype=torch.int64))
        assert extension.frame_input(step) is None
        cache = [tensor.clone() for tensor in extension.cache]
        ours = extension.step_input(step)
        assert bool(extension.skip_update) == (index == 0)
        cotangent = torch.randn(ours.shape, generator=generator)
        ours_grads = torch.autograd.grad((ours * cotangent).sum(), parameters)
        ours_cache = [tensor.clone() for tensor in extension.cache]
        for tensor, saved in zip(extension.cache, cache):
            tensor.copy_(saved)
        theirs = _old_window(extension, index)
        # (at the first frame nothing is simulated: only the rest shape moves the cached state)
        theirs_grads = [torch.zeros_like(parameter) if grad is None else grad for parameter, grad in
                        zip(parameters, torch.autograd.grad((theirs * cotangent).sum(), parameters, allow_unused=True))]
        if index > 0:  # the window moved the cloth from where the cache had it
            assert not torch.equal(ours, extension.part.skinned_rest(extension.bones[index]) + cache[0][index])
        torch.testing.assert_close(ours, theirs, rtol=0, atol=1e-6)
        for name, a, b in zip(names, ours_grads, theirs_grads):
            torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-7, msg=name)
            assert (index == 0 and name != "rest_offset_logit") or b.abs().sum() > 0, name
        for a, b in zip(ours_cache, extension.cache):
            torch.testing.assert_close(a, b, rtol=0, atol=1e-6)
        if index == 0:  # frame 0's displacement and velocity stay as they were, bit for bit
            assert all(torch.equal(a[0], b[0]) for a, b in zip(ours_cache, cache))


def test_garment_steps_train_as_the_eager_window_trained(video, tmp_path, monkeypatch):
    """Training steps with the window as device work (through the trainer's capture-ready path) end with the
    losses and the cloth the host-indexed eager window gives, through detection, densification and refreshes."""
    from warpavatar.extensions.garment import GarmentExtension

    ours = _trainer(video, tmp_path / "ours")
    our_losses = [float(ours.train_step()[1]["loss"].value) for _ in range(18)]

    def old_frame_input(self, step):  # the window computed on the host, given as the part's explicit input
        self.training = self.part is not None
        if not self.training:
            return None
        if self.cache is None or step.step - self.refreshed >= self.options.garment_refresh_every:
            self.refresh()
        return _old_window(self, step.index)

    monkeypatch.setattr(GarmentExtension, "frame_input", old_frame_input)
    monkeypatch.setattr(GarmentExtension, "step_input", lambda self, step: None)
    theirs = _trainer(video, tmp_path / "theirs")
    their_losses = [float(theirs.train_step()[1]["loss"].value) for _ in range(18)]
    part, their_part = ours.avatar.part("garment"), theirs.avatar.part("garment")
    assert part is not None and ours.gaussians.count == theirs.gaussians.count
    torch.testing.assert_close(torch.tensor(our_losses), torch.tensor(their_losses), rtol=1e-5, atol=1e-7)
    for (name, a), b in zip(part.cloth.named_parameters(), their_part.cloth.parameters()):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6, msg=name)
    moments = ours.extension("garment").optimizer.state[part.cloth.stiffness_logit]["exp_avg"]
    assert moments.abs().sum() > 0  # the cloth trained
    assert ours.extension("garment").rest_optimizer.state[part.cloth.rest_offset_logit]["exp_avg"].abs().sum() > 0
    torch.testing.assert_close(ours.gaussians.means, theirs.gaussians.means, rtol=1e-5, atol=1e-6)
    # a refresh rolls out the cloth as it is now (the fused Adam bumps no version counter, nor does a replay)
    extension = ours.extension("garment")
    extension.refresh()
    fresh = copy.deepcopy(part).rollout(extension.bones, ours.frames.seconds)
    torch.testing.assert_close(extension.cache[0], part.displacements(extension.bones, fresh[0]), rtol=0, atol=1e-6)


def test_a_steady_garment_step_reads_nothing_from_the_device(video, tmp_path):
    trainer = _after_detection(video, tmp_path, garment_refresh_every=1000)
    for _ in range(3):  # the first steps count the rasterizer's pairs (exact buffers, one read)
        trainer.train_step()
    trainer.step = 24  # past densification, the field training
    extension = trainer.extension("garment")
    assert trainer.intersection_capacity is not None and extension.step_capturable(None)
    cache = [tensor.clone() for tensor in extension.cache]
    uploads = _Uploads()
    with uploads:
        torch.tensor([1.0])  # the detector's own check: a host value made into a tensor is seen
        counts = load_tool("bench_avatar").count_step_work(trainer.train_step, device="cpu", steps=2)
    assert counts["host_reads"] == 0, counts
    assert uploads.seen > 0 and uploads.places == [], uploads.places
    assert not torch.equal(cache[0], extension.cache[0])  # the windows ran and wrote the cache back


class _Uploads(TorchDispatchMode):
    """Where the garment's and the cloth's code make tensors from host values (``lift_fresh``: ``torch.tensor``,
    ``new_tensor``) or move tensors to a device (``.to(device)``): an upload from the host on CUDA, which a CUDA
    graph capture does not allow."""

    def __init__(self):
        super().__init__()
        self.places = []
        self.seen = 0  # host values made into tensors by anyone

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        name = func.overloadpacket.__name__
        if name.startswith("lift_fresh") or (name == "_to_copy" and (kwargs or {}).get("device") is not None):
            self.seen += 1
            ours = [f"{frame.filename}:{frame.lineno}" for frame in traceback.extract_stack()
                    if any(part in frame.filename for part in ("extensions/garment.py", "/sim/"))]
            if ours:
                self.places.append(ours[-1])
        return func(*args, **(kwargs or {}))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA graphs need a CUDA device")
def test_captured_garment_steps_match_eager_steps(video, tmp_path):
    """Garment steps replayed from CUDA graphs (captured again after densification and the garment's renumbering,
    replayed across refreshes of the cached rollout) end where eager steps end, as closely as two eager runs end
    near each other: the cloth's parameters (among the avatar's) and the cache the windows wrote. (Detection at
    step 0, on the seeded initial avatar: the same garment in every run.)"""
    from tests.test_step_graph import assert_captured_run_matches

    results, caches = [], []
    for run, mode in enumerate(("on", "off", "off")):
        config = preset("quick", **{**TINY, "garment_attach": video.skeleton.names[0], "garment_from": 0})
        trainer = Trainer(video, config, tmp_path / f"{mode}{run}", device="cuda:0", cuda_graph=mode)
        losses = [float(trainer.train_step()[1]["loss"].value) for _ in range(30)]
        extension = trainer.extension("garment")
        assert extension.part is not None and extension.step_capturable(None) and extension.refreshed >= 25
        assert (trainer.graph_replays > 10) == (mode == "on")
        assert trainer.step_graph.enabled == (mode == "on")  # no capture fell back to eager steps
        parameters = {name: p.detach().clone() for name, p in trainer.avatar.named_parameters()}
        assert any(name.endswith("cloth.stiffness_logit") for name in parameters)
        results.append((losses, trainer.gaussians.count, parameters))
        caches.append([tensor.clone() for tensor in extension.cache])
    assert_captured_run_matches(*results)
    # The cached rollout amplifies the runs' small differences (on the H100, two eager runs' caches differ by
    # 0.05 on average after 30 steps, as much as a captured and an eager run's): a captured window that wrote
    # stale or misplaced states would differ by the caches' own size (0.15-0.3), so compare against the spread.
    for graph, eager, again in zip(*caches):
        gap, spread = ((run - eager).abs().mean() for run in (graph, again))
        assert gap <= 2.0 * spread + 1e-4, (float(gap), float(spread), float(eager.abs().mean()))


def test_bench_avatar_measures_a_garment_step(tmp_path):
    """``bench_kernels.py avatar --garment``: the training step row is a step with the cloth's window, captured
    on CUDA (evenly timed frames), with no host read."""
    bench = load_tool("bench_avatar")
    video, config, fitted = bench._load(None, None, "cpu", True, garment=True)
    trainer = bench._steady_trainer(video, config, fitted, "cpu", str(tmp_path), cuda_graph="off")
    row = bench._step_row(trainer, video, "cpu", 1, 2)
    assert trainer.avatar.part("garment") is not None and trainer.extension("garment").step_capturable(None)
    assert "garment: " in row["notes"] and " 0 host reads" in row["notes"] and "eager:" not in row["notes"]
