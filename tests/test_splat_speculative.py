"""The rasterizer's speculative mode: the sort buffers sized from recent calls, one read at the end of the pass.

On CUDA a call of an image size and Gaussian count seen before queues the whole pass with a guessed capacity and
reads the pair count once at the end; when the guess was short it bins and composites again with exact buffers.
These tests switch the mode on for CPU too and hold it to the exact mode: same images, same gradients, the
same errors, whatever the guess.
"""

import pytest
import torch

from warpavatar import ops
from warpavatar._src import splat as splat_bridge

from test_splat import DIFFERENTIABLE, random_cotangents, make_scene, render_and_grad


@pytest.fixture
def speculation(monkeypatch):
    """Speculation on every device, with an empty table of recent pair counts."""
    monkeypatch.setattr(splat_bridge, "_SPECULATE_ON_CPU", True)
    monkeypatch.setattr(splat_bridge, "_RECENT_PAIRS", {})
    return splat_bridge


def _key(scene, sizes):
    return (scene["means"].device, sizes["width"], sizes["height"], scene["means"].shape[0])


def _saved_sorted_ids(scene, sizes):
    scene = {name: value.detach().requires_grad_(name in DIFFERENTIABLE) for name, value in scene.items()}
    image, *_ , info = ops.rasterize_gaussians(
        scene["means"], scene["quats"], scene["scales"], scene["opacities"], scene["colors"], scene["K"],
        scene["world_to_camera"], sizes["width"], sizes["height"], background=scene["background"], return_info=True)
    return image.grad_fn.saved_pass.sorted_ids, int(info["status"][0])


def _assert_same_pass(first, second):
    (outputs_a, grads_a, _), (outputs_b, grads_b, _) = first, second
    for a, b in zip(outputs_a, outputs_b):
        assert torch.equal(a, b)
    for name in grads_a:
        # CUDA's atomic additions sum in another order on every pass: a relative bound. The scales' gradients are
        # sums of terms that cancel: in float32 the gradients differ from the float64 reference by 1.0-1.8e-4 of
        # their largest (the scales 1.3e-4; CPU, the scene of the address-graph test that changes the inputs),
        # and two passes on an H100 differed by 1.1e-5 (session 24) to 1.4e-4 (session 26). 1e-3, a third of the
        # reference tests' tolerance, is far below what a pass reading stale inputs would give.
        scale = grads_a[name].abs().max()
        assert scale > 0 and (grads_b[name] - grads_a[name]).abs().max() <= 1e-3 * scale, name


def test_a_repeated_call_speculates_and_matches_the_exact_pass(device, speculation):
    scene, sizes = make_scene(11, device=device, gaussian_count=240)
    cotangents = random_cotangents(sizes, device, 11)
    key = _key(scene, sizes)
    assert speculation._speculative_capacity(key) is None  # nothing seen: the first call is exact
    exact = render_and_grad(ops.rasterize_gaussians, scene, sizes, cotangents, densify=True)
    capacity = speculation._speculative_capacity(key)
    pairs = int(speculation._RECENT_PAIRS[key][-1])
    assert pairs > 200 and max(1024, 1.03 * pairs) <= capacity <= max(1024, 1.03 * pairs) * (1 + 1 / 64)
    speculative = render_and_grad(ops.rasterize_gaussians, scene, sizes, cotangents, densify=True)
    _assert_same_pass(exact, speculative)
    assert (speculative[2] - exact[2]).abs().max() <= 1e-5 * exact[2].abs().max()
    # The speculative pass sorted in buffers of the guessed size (padding slots sort after every tile) and kept
    # the ids of the pairs only.
    sorted_ids, pair_count = _saved_sorted_ids(scene, sizes)
    assert pair_count == pairs and sorted_ids.shape[0] == pairs < capacity


def test_a_short_guess_bins_again_with_exact_buffers(device, speculation):
    # Many small Gaussians first, then the same count made large: far more pairs than the guess allows.
    scene, sizes = make_scene(12, device=device, gaussian_count=1200, awkward=False)
    small = dict(scene, scales=scene["scales"] * 0.05)
    cotangents = random_cotangents(sizes, device, 12)
    render_and_grad(ops.rasterize_gaussians, small, sizes, cotangents)
    key = _key(scene, sizes)
    guess = speculation._speculative_capacity(key)
    speculative = render_and_grad(ops.rasterize_gaussians, scene, sizes, cotangents)
    needed = speculation._RECENT_PAIRS[key][-1]
    assert needed > guess, "the scene must outgrow the guess, or the test proves nothing"
    speculation._RECENT_PAIRS.clear()
    exact = render_and_grad(ops.rasterize_gaussians, scene, sizes, cotangents)
    _assert_same_pass(exact, speculative)
    # The guess grows to cover the largest recent call.
    assert speculation._speculative_capacity(key) >= needed



def test_rising_counts_get_their_largest_rise_on_top_of_the_last(speculation):
    key = (torch.device("cpu"), 8, 8, 2)
    for count in (20_000, 20_500, 22_000, 22_400):  # rises of 500, 1500 and 400
        speculation._remember_pairs(key, count)
    capacity = speculation._speculative_capacity(key)
    guess = 1.03 * (22_400 + 1_500)
    assert guess <= capacity <= guess * (1 + 1 / 64) and capacity % 256 == 0  # (2^15 <= capacity < 2^16: 1/128)
    speculation._remember_pairs(key, 21_000)  # a fall: the last plus the largest rise, or the most if more
    guess = 1.03 * max(22_400, 21_000 + 1_500)
    assert guess <= speculation._speculative_capacity(key) <= guess * (1 + 1 / 64) < capacity

@pytest.mark.parametrize("name", ["means", "opacities", "colors"])
def test_non_finite_inputs_raise_in_the_speculative_mode_too(device, speculation, name):
    scene, sizes = make_scene(13, device=device, gaussian_count=120)
    cotangents = random_cotangents(sizes, device, 13)
    render_and_grad(ops.rasterize_gaussians, scene, sizes, cotangents)
    assert speculation._speculative_capacity(_key(scene, sizes)) is not None
    assert_bad_value_raises(scene, sizes, cotangents, name, float("nan"))


def assert_bad_value_raises(scene, sizes, cotangents, name, value):
    """A pass whose ``name`` input holds one ``value`` (NaN or infinity) raises a message naming it."""
    bad = dict(scene)
    bad[name] = scene[name].clone()
    bad[name].view(-1)[7] = value
    with pytest.raises(ValueError, match=f"non-finite values in {name}"):
        render_and_grad(ops.rasterize_gaussians, bad, sizes, cotangents)


def test_a_fixed_capacity_neither_speculates_nor_records(device, speculation):
    scene, sizes = make_scene(14, device=device, gaussian_count=120)
    args = [scene[name] for name in ("means", "quats", "scales", "opacities", "colors", "K", "world_to_camera")]
    ops.rasterize_gaussians(*args, sizes["width"], sizes["height"], intersection_capacity=4096)
    assert speculation._RECENT_PAIRS == {}
    ops.rasterize_gaussians(*args, sizes["width"], sizes["height"])
    assert list(speculation._RECENT_PAIRS) == [_key(scene, sizes)]


def test_the_history_looks_back_a_fixed_number_of_calls(speculation):
    key = (torch.device("cpu"), 8, 8, 1)
    for count in [50_000] + [2_000] * speculation.SPECULATIVE_HISTORY:
        speculation._remember_pairs(key, count)
    assert speculation._speculative_capacity(key) == 2_080  # the 50k call has left the window (1.03 x 2000,
    speculation._remember_pairs(key, 10)                      # rounded up to 32)
    assert speculation._speculative_capacity(key) == 2_080  # a drop keeps the most
