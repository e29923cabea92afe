"""The capture-ready paths: the rasterizer with a fixed intersection capacity (no host read), the training step
without host synchronizations (and, where CUDA exists, replayed from a CUDA graph), and the playback
:class:`~warpavatar.model.playback.Player`."""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from warpavatar import _torch_impl as reference
from warpavatar import ops
from tests.test_splat import make_scene, random_cotangents, render_and_grad

def _rasterize_with(capacity):
    def rasterize(*args, **kwargs):
        return ops.rasterize_gaussians(*args, intersection_capacity=capacity, **kwargs)
    return rasterize


@pytest.mark.parametrize("seed, sh_degree", [(3, None), (4, 2)])
def test_capacity_matches_exact_buffers(seed, sh_degree):
    """Images, gradients and densification gradients are identical with a capacity that holds every pair."""
    scene, sizes = make_scene(seed, gaussian_count=300, width=48, height=40, sh_degree=sh_degree)
    cotangents = random_cotangents(sizes, "cpu", seed)
    exact = render_and_grad(ops.rasterize_gaussians, scene, sizes, cotangents, densify=True)
    *_, info = ops.rasterize_gaussians(scene["means"], scene["quats"], scene["scales"], scene["opacities"],
                                       scene["colors"], scene["K"], scene["world_to_camera"], sizes["width"],
                                       sizes["height"], sh_degree=sh_degree, return_info=True)
    pair_count = ops.rasterizer_status(info)
    assert pair_count > 300
    *_, reference_info = reference.rasterize_gaussians(
        scene["means"], scene["quats"], scene["scales"], scene["opacities"], scene["colors"], scene["K"],
        scene["world_to_camera"], sizes["width"], sizes["height"], sh_degree=sh_degree, return_info=True)
    assert ops.rasterizer_status(reference_info) == pair_count
    for capacity in (pair_count, 2 * pair_count + 17):
        outputs, grads, densify = render_and_grad(_rasterize_with(capacity), scene, sizes, cotangents, densify=True)
        assert all(torch.equal(a, b) for a, b in zip(outputs, exact[0]))
        assert grads.keys() == exact[1].keys()
        assert all(torch.equal(grads[name], exact[1][name]) for name in grads)
        assert torch.equal(densify, exact[2])


def test_capacity_overflow_is_flagged_not_fatal():
    scene, sizes = make_scene(5, gaussian_count=300, width=48, height=40)
    args = [scene[k] for k in ("means", "quats", "scales", "opacities", "colors", "K", "world_to_camera")]
    image, _, _, info = ops.rasterize_gaussians(*args, sizes["width"], sizes["height"], return_info=True)
    needed = ops.rasterizer_status(info)
    short, _, _, short_info = ops.rasterize_gaussians(*args, sizes["width"], sizes["height"], return_info=True,
                                                      intersection_capacity=needed // 2)
    assert ops.rasterizer_status(short_info) == needed  # the count needed, past the capacity
    assert torch.isfinite(short).all() and not torch.equal(short, image)
    # non-finite input: the exact path raises at once, the capped path flags it on the device
    args[0] = args[0].clone()
    args[0][7, 1] = float("nan")
    with pytest.raises(ValueError, match="non-finite values in means"):
        ops.rasterize_gaussians(*args, sizes["width"], sizes["height"])
    *_, bad_info = ops.rasterize_gaussians(*args, sizes["width"], sizes["height"], return_info=True,
                                           intersection_capacity=2 * needed)
    with pytest.raises(ValueError, match="non-finite values in means"):
        ops.rasterizer_status(bad_info)
    with pytest.raises(ValueError, match="intersection_capacity"):
        ops.rasterize_gaussians(*args, sizes["width"], sizes["height"], intersection_capacity=0)


# ------------------------------------------------------------------------------------------------ playback
@pytest.fixture(scope="module")
def demo_video():
    from warpavatar import data

    return data.load_video_folder(data.demo_subject_path() / "train", scale=0.25)


def _playback_avatar(video):
    from tests.conftest import small_avatar
    from warpavatar.extensions.pose_correction import PoseCorrection

    avatar = small_avatar(video.skeleton, seed=3, per_bone=40, cells=8, distill_steps=5, random_frames=True)
    field = avatar.field
    part = PoseCorrection(field.bbox_min, field.bbox_max, torch.as_tensor(video.skeleton.parents), hidden=16)
    with torch.no_grad():  # a correction that is not the identity
        for parameter in part.parameters():
            parameter.normal_(0.0, 0.05)
    avatar.add_part(part)
    return avatar


def test_player_draws_what_render_draws(demo_video):
    from warpavatar.model.playback import Player

    avatar = _playback_avatar(demo_video)
    background = torch.tensor([0.2, 0.3, 0.4])
    player = Player(avatar, demo_video.cameras[0], background=background, cuda_graph="off", check_every=2)
    assert player.capacity is None and not player.use_graph
    for frame in (0, 3, 5, 2):
        camera = demo_video.cameras[frame]
        bones = torch.as_tensor(demo_video.bone_transforms[frame], dtype=torch.float32)
        image, alpha, depth = player.render(bones, camera=camera)
        with torch.no_grad():
            expected = avatar.render(camera, bones, background=background)
        for ours, theirs in zip((image, alpha, depth), expected):  # the player's correction kernel rounds its own way
            torch.testing.assert_close(ours, theirs, rtol=1e-5, atol=1e-5)
        assert alpha.max() > 0.5
    assert player.capacity is not None


def test_player_grows_a_capacity_that_overflowed(demo_video):
    from warpavatar.model.playback import Player

    avatar = _playback_avatar(demo_video)
    player = Player(avatar, demo_video.cameras[0], cuda_graph="off", check_every=1)
    bones = torch.as_tensor(demo_video.bone_transforms[1], dtype=torch.float32)
    player.render(bones)
    player.capacity = 10  # far too small: the check sees it, grows the capacity and draws the frame again
    image, _, _ = player.render(bones)
    assert player.capacity > 1000
    with torch.no_grad():
        torch.testing.assert_close(image, avatar.render(demo_video.cameras[0], bones)[0], rtol=1e-5, atol=1e-5)
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="cuda-graph on needs a CUDA device"):
            Player(avatar, demo_video.cameras[0], cuda_graph="on")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="the status copies to pinned memory need CUDA")
def test_capacity_poll_reads_the_status_without_waiting_and_at_most_lag_late():
    from warpavatar.model.capacity import IntersectionCapacity

    # Made before the device is kept busy below: a copy from pageable host memory would wait for it.
    rows = [[9_500, 0], [15_000, 0], [9_000, 0], [10, 1]]  # [pair count, input flags]
    status = dict(zip((pairs for pairs, _ in rows), torch.tensor(rows, dtype=torch.int32, device="cuda:0")))
    capacity = IntersectionCapacity("cuda:0", factor=1.5)
    capacity.value = 10_000  # (the smallest capacity is 1024)
    capacity.record(status[9_500])
    assert capacity.poll(max_lag=3) is None and capacity.value == 10_000  # its copy queued, nothing read yet
    torch.cuda.synchronize()
    capacity.record(status[15_000])  # a frame past the capacity
    torch.cuda._sleep(50_000_000)  # the device busy for a while: the copy queued next stays in flight
    assert capacity.poll(max_lag=3) is None and capacity.value == 14_250  # 9500 read: near, grown
    capacity.record(status[9_000])
    assert capacity.poll(max_lag=3) is None and capacity.value == 14_250  # 15000 in flight: no wait
    assert capacity.poll(max_lag=3) == 15_000 and capacity.value == 22_500  # the third poll waits: an overflow
    capacity.record(status[10])  # flagged: non-finite input
    with pytest.raises(ValueError):
        capacity.poll(max_lag=1)  # reads at once


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA graphs need a CUDA device")
def test_player_graph_replays_match_eager_frames(demo_video):
    from warpavatar.model.playback import Player

    avatar = _playback_avatar(demo_video).to("cuda:0")
    background = torch.tensor([0.2, 0.3, 0.4], device="cuda:0")
    graphed = Player(avatar, demo_video.cameras[0], background=background, cuda_graph="on", check_every=3)
    eager = Player(avatar, demo_video.cameras[0], background=background, cuda_graph="off", check_every=3)
    assert graphed.use_graph
    for frame in (0, 1, 4, 2, 6, 3):
        bones = torch.as_tensor(demo_video.bone_transforms[frame], dtype=torch.float32, device="cuda:0")
        ours = [t.clone() for t in graphed.render(bones, camera=demo_video.cameras[frame])]
        theirs = eager.render(bones, camera=demo_video.cameras[frame])
        for a, b in zip(ours, theirs):  # atomics in the compositing may round differently
            torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5)
    assert graphed._graph is not None


# ------------------------------------------------------------------------------------------------ training step
def _tiny_trainer(video_folder, tmp_path, *, device="cpu", cuda_graph="off", **overrides):
    from warpavatar.fit import Trainer, preset

    values = dict(iterations=60, image_scale=0.25, max_train_frames=6, init_points_per_bone=20,
                  init_carve_candidates=4000, init_carve_points=300, sh_degree=1, sh_increase_every=8,
                  grid_cells=12, grid_min_cells=4, field_hidden=16, field_layers=1, field_warmup_steps=0,
                  gaussian_only_steps=4, densify_from=6, densify_until=14, densify_every=6,
                  densify_grad_threshold=1e-6, opacity_reset_every=12, pose_correction=True,
                  pose_correction_hidden=16, log_every=1000, checkpoint_every=100000, preview_frames=0)
    values.update(overrides)
    return Trainer(video_folder, preset("quick", **values), tmp_path, device=device, cuda_graph=cuda_graph)


@pytest.fixture(scope="module")
def small_video():
    from warpavatar import data

    return data.load_video_folder(data.demo_subject_path() / "train", scale=0.25)


def test_steady_training_step_reads_nothing_from_the_device(small_video, tmp_path):
    from tests.conftest import load_tool

    trainer = _tiny_trainer(small_video, tmp_path)
    for _ in range(3):  # the first step counts the rasterizer's pairs (exact buffers, one read)
        trainer.train_step()
    trainer.step = 20  # past densification, the field training
    trainer.train_step()  # the field's first training step chooses its active grid points (--field-cells: one read)
    assert trainer.intersection_capacity is not None and trainer.extension("pose_correction") is not None
    counter = load_tool("bench_avatar")._OpCounter()
    with counter:
        for _ in range(2):
            trainer.train_step()
    assert counter.host_reads == 0, counter.ops
    assert sum(counter.ops.values()) > 300


def test_refining_steps_read_nothing_from_the_device_and_may_be_captured(small_video, tmp_path):
    """Pose refinement takes the step's frame from the device buffer and changes its learning rates in place: its
    steps, while refining and after, are capturable and read nothing back, and the frame's refined pose is the
    one the step trains (a replayed step would otherwise train the captured step's frame)."""
    from tests.conftest import load_tool

    trainer = _tiny_trainer(small_video, tmp_path, refine_poses="on", refine_poses_from=2, refine_poses_until=40)
    extension = trainer.extension("pose_refinement")
    for _ in range(3):
        trainer.train_step()
    trainer.step = 20  # refining, past densification
    trainer.train_step()
    counter = load_tool("bench_avatar")._OpCounter()
    rates = [float(group["lr"]) for group in extension.optimizer.param_groups]
    with counter:
        step, _ = trainer.train_step()
    assert counter.host_reads == 0, counter.ops
    assert extension.step_capturable(step) and extension.frame_input(step) is None
    options, extension.options = extension.options, replace(extension.options, pose_moments="component")
    assert not extension.step_capturable(step)  # plain Adam's steps stay eager
    extension.options = options
    assert all(float(group["lr"]) < rate for group, rate in zip(extension.optimizer.param_groups, rates))  # decays
    pulls = extension.part.rotation.grad.abs().sum((-2, -1))  # the priors pull every frame a little, the
    others = torch.cat([pulls[:step.index], pulls[step.index + 1:]])  # images the step's frame only
    assert float(pulls[step.index]) > 5 * float(others.max()) > 0
    trainer.step = 41  # refinement over: the poses stay as they are, the step still needs no host read
    before = extension.part.rotation.detach().clone()
    with counter:
        trainer.train_step()
    assert counter.host_reads == 0 and torch.equal(extension.part.rotation, before)


def test_no_autograd_graph_outlives_its_step(small_video, tmp_path):
    """What a step returns and what the trainer keeps after it hold no autograd graph: a kept graph keeps the
    parameters' AccumulateGrad nodes bound to the stream that made them, which invalidates the next capture."""
    trainer = _tiny_trainer(small_video, tmp_path)
    trainer.step = 20  # the field trains: its grid has a graph during the step
    for _ in range(2):
        step, terms = trainer.train_step()
    kept = [term.value for term in terms.values()] + [step.image, step.alpha]
    kept += [value for value in step.posed.values() if isinstance(value, torch.Tensor)]
    kept.append(trainer.skinning.grid(step.step, train_field=True))  # the step's cached grid
    assert len(kept) > 10
    assert not any(tensor.requires_grad or tensor.grad_fn is not None for tensor in kept)


def test_sync_free_steps_fit_what_exact_steps_fit(small_video, tmp_path, monkeypatch):
    """With the fixed-capacity rasterizer and static buffers, a fit through densification, an opacity reset and
    the start of the field's training ends bit for bit where the exact, synchronizing rasterizer ends."""
    from warpavatar.model import Avatar

    steps = 16
    fast = _tiny_trainer(small_video, tmp_path / "fast")
    initial_count = fast.gaussians.count
    for _ in range(steps):
        fast.train_step()
    exact_rasterize = Avatar.rasterize
    monkeypatch.setattr(Avatar, "rasterize", lambda self, *args, intersection_capacity=None, **kwargs:
                        exact_rasterize(self, *args, **kwargs))
    exact = _tiny_trainer(small_video, tmp_path / "exact")
    for _ in range(steps):
        exact.train_step()
    assert fast.gaussians.count == exact.gaussians.count != 0
    assert fast.gaussians.count != initial_count  # it densified
    for (name, ours), (_, theirs) in zip(fast.avatar.named_parameters(), exact.avatar.named_parameters()):
        assert torch.equal(ours, theirs), name
    assert torch.equal(fast.density.grad_accum, exact.density.grad_accum)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA graphs need a CUDA device")
def test_captured_steps_match_eager_steps(small_video, tmp_path):
    """16 steps replayed from CUDA graphs (captured again after densification) end where eager steps end, as
    closely as two eager runs end near each other (the compositing's atomic additions run in no fixed order, and
    Adam turns their rounding into differences of up to its learning rate on parameters with tiny gradients)."""
    results = []
    for run, mode in enumerate(("on", "off", "off")):
        trainer = _tiny_trainer(small_video, tmp_path / f"{mode}{run}", device="cuda:0", cuda_graph=mode)
        losses = []
        for _ in range(16):  # the field from 4, densification at 6 and 12: captures, replays, captures again
            _, terms = trainer.train_step()
            losses.append(float(terms["loss"].value))
        assert (trainer.graph_replays > 5) == (mode == "on")
        assert trainer.step_graph.enabled == (mode == "on")  # no capture fell back to eager steps
        results.append((losses, trainer.gaussians.count,
                        {name: p.detach().clone() for name, p in trainer.avatar.named_parameters()}))
    assert_captured_run_matches(*results)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA graphs need a CUDA device")
def test_captured_refining_steps_match_eager_steps(small_video, tmp_path):
    """Steps that refine the poses, replayed from CUDA graphs, end where eager steps end: the refined poses too
    (each replay trains its own frame's pose at the learning rate of its step)."""
    results = []
    for run, mode in enumerate(("on", "off", "off", "on")):
        trainer = _tiny_trainer(small_video, tmp_path / f"{mode}{run}", device="cuda:0", cuda_graph=mode,
                                refine_poses="on", refine_poses_from=2, refine_poses_until=14)
        losses = []
        for _ in range(18):  # refining from 2 to 14, then fixed poses: captured again at each change
            _, terms = trainer.train_step()
            losses.append(float(terms["loss"].value))
        assert (trainer.graph_replays > 5) == (mode == "on")
        assert trainer.step_graph.enabled == (mode == "on")
        results.append((losses, trainer.gaussians.count,
                        {name: p.detach().clone() for name, p in trainer.avatar.named_parameters()}))
    # Adam turns the compositing's atomic rounding into moves of up to a learning rate, and through the refined
    # pose into most Gaussians: two runs of either kind differ by a few percent of their elements (on the H100:
    # 2.4 % captured against eager, 3.6 % eager against eager, 3.3 % captured against captured), so the spread is
    # taken over both pairs of like runs.
    assert_captured_run_matches(*results)
    graph, eager, again, graph_again = (result[2]["parts.pose_refinement.rotation"] for result in results)
    assert float(eager.abs().max()) > 1e-5  # it refined
    spread = max(float((again - eager).abs().max()), float((graph_again - graph).abs().max()))
    assert float((graph - eager).abs().max()) <= 2.0 * spread + 1e-6


def assert_captured_run_matches(graph, eager, again, graph_again=None) -> None:
    """A run of captured steps ended as close to an eager run as a second eager run did, or, given a second
    captured run, as the more distant of the like pairs (eager and eager, captured and captured): each run is (its
    losses, its Gaussian count, {name: parameter})."""
    like = [(again, eager)] + ([] if graph_again is None else [(graph_again, graph)])
    assert graph[2].keys() == eager[2].keys()
    # Densification thresholds accumulated gradients, so that rounding may also clone or split a few Gaussians
    # more in one run than in another (on the H100: 5,436 against 5,431 after 30 garment steps), and the runs'
    # losses then drift apart by up to about 1 %: the captured run's losses may differ from the eager run's as
    # much as a like pair's do (twice that, plus rounding), and when the counts differ the runs' Gaussians no
    # longer pair up, so the losses are the comparison.
    def loss_gap(a, b) -> float:
        return float((torch.tensor(a[0], dtype=torch.float64) - torch.tensor(b[0], dtype=torch.float64)).abs().max())

    gap, spread = loss_gap(graph, eager), max(loss_gap(a, b) for a, b in like)
    assert gap <= 2.0 * spread + 1e-5 + 1e-3 * max(abs(v) for v in eager[0]), (gap, spread)
    count_spread = max(abs(a[1] - b[1]) for a, b in like)
    assert abs(graph[1] - eager[1]) <= max(2 * count_spread, 0.002 * eager[1]), (graph[1], eager[1], count_spread)
    if graph[1] != eager[1] or count_spread:
        return
    # A few elements jump by up to a learning rate between any two runs; a captured step that read a stale input
    # (a learning rate, a frame, a grid) would move most of them: compare the share of elements that moved.
    def moved(a, b, name) -> float:
        return float(((a[2][name] - b[2][name]).abs() > 1e-4).float().mean())

    for name in graph[2]:
        spread = max(moved(a, b, name) for a, b in like)
        assert moved(graph, eager, name) <= 2.0 * spread + 0.01, (name, moved(graph, eager, name), spread)


def test_bench_kernels_avatar_quick_runs(capsys):
    from tests.conftest import load_tool

    assert load_tool("bench_kernels").main(["avatar", "--quick", "--device", "cpu"]) == 0
    table = capsys.readouterr().out
    for measure in ("rasterizer fwd / fwd+bwd ms", "training step ms (eager)", "playback FPS (eager)"):
        assert measure in table
    assert "0 host reads" in table
