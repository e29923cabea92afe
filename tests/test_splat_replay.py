"""The rasterizer's replayed passes: a shape's fixed-capacity pass captured once calls of it repeat, then replayed.

On CUDA a replay is a CUDA graph; on CPU (switched on here) the same fixed-capacity pass runs again on the same
fixed tensors, so everything around the graph (inputs copied in, outputs copied out, status read, a graph
outgrown, the cache's bounds) is held to the exact mode on every device.
"""

import pytest
import torch

from warpavatar import ops
from warpavatar._src import splat as splat_bridge
from warpavatar._src.graphs import address_graphs, splat_replay

from test_splat import DIFFERENTIABLE, make_scene, random_cotangents, render, render_and_grad
from test_splat_speculative import _assert_same_pass, assert_bad_value_raises


@pytest.fixture
def replays(monkeypatch):
    """Speculation and replays on every device, with an empty table of pair counts and no graph cached."""
    monkeypatch.setattr(splat_bridge, "_SPECULATE_ON_CPU", True)
    monkeypatch.setattr(splat_replay, "_REPLAY_ON_CPU", True)
    monkeypatch.setattr(splat_replay, "REPLAY_AFTER", 3)
    monkeypatch.setattr(splat_bridge, "_RECENT_PAIRS", {})
    cache = splat_replay.ReplayCache(run_pass=splat_bridge.run_pass, buffer_type=splat_bridge.PassBuffers,
                                     tile_grid=splat_bridge._tile_grid,
                                     raise_on_bad_inputs=splat_bridge._raise_on_bad_inputs)
    monkeypatch.setattr(splat_bridge, "_REPLAYS", cache)
    return cache


def _exact(scene, sizes, cotangents, **options):
    """The exact mode's pass (nothing remembered, nothing replayed), leaving the tables as they were."""
    saved = dict(splat_bridge._RECENT_PAIRS)
    splat_bridge._RECENT_PAIRS.clear()
    try:
        return render_and_grad(ops.rasterize_gaussians, scene, sizes, cotangents, **options)
    finally:
        splat_bridge._RECENT_PAIRS.clear()
        splat_bridge._RECENT_PAIRS.update(saved)


def _assert_same_as_exact(scene, sizes, cotangents, replayed, *, like_pairs: int = 3):
    """Outputs bit-equal to the exact pass's; gradients within four times what exact passes differ by among
    themselves (CUDA's atomic additions sum in another order every pass; on CPU they are equal), or 1e-4 of their
    largest value. The spread is the largest over ``like_pairs`` pairs of exact passes: a replayed pass differs
    from an exact one as one exact pass does from another, and one pair's spread alone is sometimes small."""
    exact = [_exact(scene, sizes, cotangents, densify=True) for _ in range(like_pairs + 1)]
    first = exact[0]
    for a, b in zip(first[0], replayed[0]):
        assert torch.equal(a, b)

    def gradients(result):
        return {**result[1], "densify": result[2]}

    for name, a in gradients(first).items():
        scale = a.abs().max()
        spread = max((gradients(other)[name] - a).abs().max() for other in exact[1:])
        assert scale > 0 and (gradients(replayed)[name] - a).abs().max() <= max(4 * spread, 1e-4 * scale), name


def _calls_until_replayed(scene, sizes, cotangents, cache):
    """Calls until the shape's pass is captured: the first is exact, then REPLAY_AFTER speculative ones."""
    for _ in range(1 + splat_replay.REPLAY_AFTER):
        render_and_grad(ops.rasterize_gaussians, scene, sizes, cotangents)
    assert cache.captures == 1


def _moved(scene, seed):
    """The same shape with other values: every Gaussian moved and recoloured, another background."""
    generator = torch.Generator().manual_seed(seed)
    moved = dict(scene)
    device = scene["means"].device
    moved["means"] = scene["means"] + 0.05 * torch.randn(scene["means"].shape, generator=generator).to(device)
    moved["colors"] = torch.rand(scene["colors"].shape, generator=generator).to(device)
    moved["background"] = torch.rand(3, generator=generator).to(device)
    return moved


@pytest.mark.parametrize("sh_degree", [None, 2])
def test_repeated_calls_are_replayed_and_match_the_exact_pass(device, replays, sh_degree):
    scene, sizes = make_scene(21, device=device, gaussian_count=300, sh_degree=sh_degree)
    cotangents = random_cotangents(sizes, device, 21)
    _calls_until_replayed(scene, sizes, cotangents, replays)
    for seed in (1, 2):  # other values of the same shape: the inputs are copied in, not baked into the graph
        moved = _moved(scene, seed)
        replayed = render_and_grad(ops.rasterize_gaussians, moved, sizes, cotangents, densify=True)
        _assert_same_as_exact(moved, sizes, cotangents, replayed)
    assert replays.replays == 2 and replays.captures == 1
    replay = next(iter(replays._replays.values()))
    fixed = sum(t.numel() * t.element_size() for t in (replay._inputs, *replay._outputs))
    scratch = 4 * (300 + 2) + 24 * 300 + 16 * replay.capacity
    assert replays.held_bytes() == fixed + scratch
    replays.clear()
    assert replays.held_bytes() == 0


def test_a_replayed_pass_returns_tensors_of_its_own(device, replays):
    scene, sizes = make_scene(22, device=device, gaussian_count=200)
    cotangents = random_cotangents(sizes, device, 22)
    _calls_until_replayed(scene, sizes, cotangents, replays)
    first = render(ops.rasterize_gaussians, scene, sizes, return_info=True)
    kept = [tensor.clone() for tensor in first[:3]] + [first[3]["radii"].clone(), first[3]["status"].clone()]
    second = render(ops.rasterize_gaussians, _moved(scene, 3), sizes, return_info=True)
    assert replays.replays == 2
    assert not torch.equal(first[0], second[0])
    for before, after in zip(kept, list(first[:3]) + [first[3]["radii"], first[3]["status"]]):
        assert torch.equal(before, after)  # the second replay did not write into the first call's outputs
    # and the first call's backward still reads its own saved state
    scene_grad = {name: value.detach().requires_grad_(name in DIFFERENTIABLE) for name, value in scene.items()}
    densify = torch.zeros(scene["means"].shape[0], 2, device=device)
    outputs = render(ops.rasterize_gaussians, scene_grad, sizes, densify_grad_out=densify)
    render(ops.rasterize_gaussians, _moved(scene, 4), sizes)
    grads = torch.autograd.grad(outputs, [scene_grad[name] for name in DIFFERENTIABLE], cotangents)
    assert replays.replays == 4
    _assert_same_as_exact(scene, sizes, cotangents, (outputs, dict(zip(DIFFERENTIABLE, grads)), densify))


def test_an_outgrown_graph_passes_exactly_and_is_captured_again(device, replays):
    scene, sizes = make_scene(23, device=device, gaussian_count=1200, awkward=False)
    small = dict(scene, scales=scene["scales"] * 0.05)
    cotangents = random_cotangents(sizes, device, 23)
    _calls_until_replayed(small, sizes, cotangents, replays)
    key = next(iter(replays._replays))
    capacity = replays._replays[key].capacity
    grown = render_and_grad(ops.rasterize_gaussians, scene, sizes, cotangents)
    needed = splat_bridge._RECENT_PAIRS[(scene["means"].device, sizes["width"], sizes["height"], 1200)][-1]
    assert needed > capacity, "the scene must outgrow the graph, or the test proves nothing"
    _assert_same_pass(_exact(scene, sizes, cotangents), grown)
    assert key not in replays._replays and replays.replays == 0
    for _ in range(splat_replay.REPLAY_AFTER):  # fitting calls again: captured at the grown capacity
        render_and_grad(ops.rasterize_gaussians, scene, sizes, cotangents)
    assert replays.captures == 2 and replays._replays[key].capacity >= needed


@pytest.mark.parametrize("name", ["means", "scales", "colors"])
def test_non_finite_inputs_raise_in_a_replay_too(device, replays, name):
    scene, sizes = make_scene(24, device=device, gaussian_count=150)
    cotangents = random_cotangents(sizes, device, 24)
    _calls_until_replayed(scene, sizes, cotangents, replays)
    assert_bad_value_raises(scene, sizes, cotangents, name, float("inf"))


def test_only_consecutive_fitting_calls_of_one_shape_capture(device, replays):
    first, sizes = make_scene(25, device=device, gaussian_count=100)
    second, _ = make_scene(26, device=device, gaussian_count=140)
    cotangents = random_cotangents(sizes, device, 25)
    for _ in range(3 * splat_replay.REPLAY_AFTER):  # alternating shapes never make a streak
        render_and_grad(ops.rasterize_gaussians, first, sizes, cotangents)
        render_and_grad(ops.rasterize_gaussians, second, sizes, cotangents)
    assert replays.captures == 0
    args = [first[name] for name in ("means", "quats", "scales", "opacities", "colors", "K", "world_to_camera")]
    for _ in range(2 * splat_replay.REPLAY_AFTER):  # a fixed capacity neither counts nor replays
        ops.rasterize_gaussians(*args, sizes["width"], sizes["height"], intersection_capacity=4096)
    assert replays.captures == 0 and replays.replays == 0


def test_the_cache_keeps_a_bounded_number_of_shapes(device, replays, monkeypatch):
    monkeypatch.setattr(splat_replay, "REPLAYS_KEPT", 2)
    keys = []
    for index, count in enumerate((90, 110, 130)):
        scene, sizes = make_scene(30 + index, device=device, gaussian_count=count)
        cotangents = random_cotangents(sizes, device, 30)
        for _ in range(1 + splat_replay.REPLAY_AFTER):
            render_and_grad(ops.rasterize_gaussians, scene, sizes, cotangents)
        keys.append((scene["means"].device, sizes["width"], sizes["height"], count, -1, 1))
    assert replays.captures == 3
    assert list(replays._replays) == keys[1:]  # the least recently used went first


def test_a_graph_far_larger_than_recent_calls_need_is_dropped(device, replays):
    scene, sizes = make_scene(27, device=device, gaussian_count=800, awkward=False)
    cotangents = random_cotangents(sizes, device, 27)
    _calls_until_replayed(dict(scene, scales=scene["scales"] * 3), sizes, cotangents, replays)
    large = next(iter(replays._replays.values())).capacity
    tiny = dict(scene, scales=scene["scales"] * 0.02)
    for _ in range(splat_bridge.SPECULATIVE_HISTORY + 1):  # until the history has forgotten the large calls
        result = render_and_grad(ops.rasterize_gaussians, tiny, sizes, cotangents)
    assert not replays._replays  # dropped on the call that found it over SHRINK_FACTOR times the guess
    _assert_same_pass(_exact(tiny, sizes, cotangents), result)
    for _ in range(splat_replay.REPLAY_AFTER):
        render_and_grad(ops.rasterize_gaussians, tiny, sizes, cotangents)
    small = next(iter(replays._replays.values())).capacity
    assert replays.captures == 2 and small * splat_replay.SHRINK_FACTOR < large


def test_layouts_carve_the_arenas_end_to_end():
    layouts = splat_replay.pass_layouts(5, 7, 3, 4, 50)
    for layout in layouts:
        words = sum(torch.Size(shape).numel() for _, shape, _ in layout)
        arena = torch.arange(words, dtype=torch.int32)
        views = splat_replay.carve(arena, layout)
        starts = [view.view(torch.int32).reshape(-1)[0].item() if view.dtype != torch.int32
                  else view.reshape(-1)[0].item() for view in views.values()]
        sizes = [view.numel() for view in views.values()]
        assert starts == [sum(sizes[:i]) for i in range(len(sizes))] and sum(sizes) == words


def test_a_shape_too_large_to_hold_stays_eager(device, replays, monkeypatch):
    scene, sizes = make_scene(28, device=device, gaussian_count=200)
    cotangents = random_cotangents(sizes, device, 28)
    monkeypatch.setattr(splat_replay, "REPLAY_MAX_BYTES", 1000)
    for _ in range(2 + 2 * splat_replay.REPLAY_AFTER):
        result = render_and_grad(ops.rasterize_gaussians, scene, sizes, cotangents)
    assert replays.captures == 0 and replays.replays == 0 and replays.held_bytes() == 0
    assert list(replays._replays.values()) == [None]  # remembered, so no capture is tried again
    _assert_same_pass(_exact(scene, sizes, cotangents), result)


@pytest.mark.parametrize("captured_in_inference", [True, False])
def test_replays_serve_callers_in_and_out_of_inference_mode(device, replays, captured_in_inference):
    scene, sizes = make_scene(29, device=device, gaussian_count=160)
    cotangents = random_cotangents(sizes, device, 29)
    first_mode = torch.inference_mode() if captured_in_inference else torch.no_grad()
    with first_mode:
        for _ in range(1 + splat_replay.REPLAY_AFTER):
            render(ops.rasterize_gaussians, scene, sizes)
    assert replays.captures == 1
    moved = _moved(scene, 5)
    replayed = render_and_grad(ops.rasterize_gaussians, moved, sizes, cotangents, densify=True)  # with autograd
    with torch.inference_mode():
        inferred = render(ops.rasterize_gaussians, moved, sizes)
    assert replays.replays == 2
    _assert_same_as_exact(moved, sizes, cotangents, replayed)
    for a, b in zip(inferred, replayed[0]):
        assert torch.equal(a, b)


def test_the_public_switch_sets_the_mode_and_releases_the_graphs_memory(device, replays, monkeypatch):
    """``ops.rasterizer_replays``: ``mode="off"`` keeps every call eager; ``"owned"`` captures after ``after``
    calls in a row; each call returns the bytes the owned graphs held and releases them; the default mode is
    ``"address"``; bad values are clear errors."""
    monkeypatch.setattr(splat_replay, "REPLAY_AFTER", splat_replay.REPLAY_AFTER)  # (restored after the test)
    monkeypatch.setattr(splat_replay, "REPLAY_MAX_BYTES", splat_replay.REPLAY_MAX_BYTES)
    monkeypatch.setattr(address_graphs, "CAPTURE_AFTER", address_graphs.CAPTURE_AFTER)
    scene, sizes = make_scene(23, device=device, gaussian_count=200)
    cotangents = random_cotangents(sizes, device, 23)
    assert ops.rasterizer_replays(mode="off") == 0
    assert address_graphs.CAPTURE_AFTER is None and splat_replay.REPLAY_AFTER is None
    for _ in range(6):
        render_and_grad(ops.rasterize_gaussians, scene, sizes, cotangents)
    assert replays.captures == 0 and replays.held_bytes() == 0
    ops.rasterizer_replays(mode="owned", after=1)
    for _ in range(3):  # an exact call, one speculative, then the replay's capture
        render_and_grad(ops.rasterize_gaussians, scene, sizes, cotangents)
    assert replays.captures == 1 and address_graphs.CAPTURE_AFTER is None
    held = replays.held_bytes()
    assert held > 0 and ops.rasterizer_replays() == held and replays.held_bytes() == 0
    assert splat_replay.REPLAY_AFTER is None and address_graphs.CAPTURE_AFTER == address_graphs.DEFAULT_CAPTURE_AFTER
    for bad in (dict(mode="fast"), dict(after=0), dict(after=1.5), dict(max_bytes=0)):
        with pytest.raises(ValueError, match=next(iter(bad))):
            ops.rasterizer_replays(**bad)
