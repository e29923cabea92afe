"""Work replayed from CUDA graphs keyed by the addresses it touches (``warpavatar._src.graphs.address_graphs``), and the
rasterizer's speculative passes replayed that way.

On CUDA a key seen twice is captured and later calls of it replay the graph; on CPU every call runs eagerly. The
replayed work must read the current values of its buffers, and the rasterizer's replayed passes must match its
exact mode, call after call, whether its buffers' addresses repeat or not.
"""

import pytest
import torch

from warpavatar import ops
from warpavatar._src import splat as splat_bridge
from warpavatar._src.graphs import address_graphs
from warpavatar._src.graphs.address_graphs import AddressKeyedGraphs

from test_splat import DIFFERENTIABLE, make_scene, random_cotangents, render_and_grad
from test_splat_speculative import _assert_same_pass


def _is_cuda(device) -> bool:
    return torch.device(device).type == "cuda"


def test_a_repeated_key_replays_its_work_on_the_current_values(device):
    graphs = AddressKeyedGraphs()
    source = torch.rand(3000, device=device)
    target = torch.empty_like(source)
    key = (device, source.data_ptr(), target.data_ptr(), source.numel())
    for _ in range(6):
        source.uniform_(-2.0, 5.0)  # the same addresses, new values
        graphs.run(key, lambda: target.copy_(source).mul_(3.0), device=torch.device(device))
        assert torch.equal(target, source * 3.0)
    if _is_cuda(device):  # eager, captured on the second sight, then replayed
        assert (graphs.eager, graphs.captures, graphs.replays) == (1, 1, 4)
    else:
        assert (graphs.eager, graphs.captures, graphs.replays) == (6, 0, 0)


def test_keys_do_not_share_graphs_and_the_least_recent_is_dropped(device, monkeypatch):
    monkeypatch.setattr(address_graphs, "GRAPHS_KEPT", 2)
    graphs = AddressKeyedGraphs()
    sources = [torch.rand(500, device=device) for _ in range(3)]
    targets = [torch.zeros(500, device=device) for _ in range(3)]

    def call(index):
        source, target = sources[index], targets[index]
        source.normal_()
        graphs.run((index, source.data_ptr(), target.data_ptr()), lambda: target.copy_(source).add_(index),
                   device=torch.device(device))
        assert torch.equal(target, source + index)

    for index in (0, 1, 0, 1, 0, 1):
        call(index)
    for index in (2, 2, 2, 1, 1):  # a third key pushes out the least recent graph (0's); 1's still replays
        call(index)
    if _is_cuda(device):
        assert graphs.captures == 3 and graphs.replays == 2 + 1 + 2
        call(0)  # dropped: counted again from nothing, so it runs eagerly
        assert graphs.captures == 3 and graphs.eager == 2 + 1 + 1
    else:
        assert graphs.eager == 11 and graphs.captures == graphs.replays == 0


def test_a_failed_capture_warns_and_leaves_the_key_eager(device):
    if not _is_cuda(device):
        pytest.skip("CPU work is never captured")
    graphs = AddressKeyedGraphs()
    source = torch.rand(100, device=device)
    target = torch.zeros_like(source)
    calls = []

    def queue():
        calls.append(torch.cuda.is_current_stream_capturing())
        if calls[-1]:
            raise RuntimeError("this work cannot be captured")
        target.copy_(source)

    key = (source.data_ptr(), target.data_ptr())
    graphs.run(key, queue, device=torch.device(device))
    with pytest.warns(RuntimeWarning, match="stays eager"):
        graphs.run(key, queue, device=torch.device(device))
    for _ in range(3):
        source.uniform_()
        graphs.run(key, queue, device=torch.device(device))
        assert torch.equal(target, source)
    assert calls == [False, True, False, False, False, False] and graphs.captures == 0


@pytest.fixture
def pass_graphs(monkeypatch):
    """Speculation on every device, a fresh table of pair counts and fresh pass graphs."""
    monkeypatch.setattr(splat_bridge, "_SPECULATE_ON_CPU", True)
    monkeypatch.setattr(splat_bridge, "_RECENT_PAIRS", {})
    graphs = AddressKeyedGraphs()
    monkeypatch.setattr(splat_bridge, "_PASS_GRAPHS", graphs)
    return graphs


def _exact(scene, sizes, cotangents):
    """The exact mode's pass on the scene's current values (no recent pair counts: no speculation, no graph)."""
    saved = dict(splat_bridge._RECENT_PAIRS)
    splat_bridge._RECENT_PAIRS.clear()
    try:
        return render_and_grad(ops.rasterize_gaussians, scene, sizes, cotangents, densify=True)
    finally:
        splat_bridge._RECENT_PAIRS.clear()
        splat_bridge._RECENT_PAIRS.update(saved)


@pytest.mark.parametrize("keep_outputs", [False, True], ids=["released", "kept"])
def test_replayed_passes_match_the_exact_pass_as_inputs_change(device, pass_graphs, keep_outputs):
    scene, sizes = make_scene(21, device=device, gaussian_count=300)
    cotangents = random_cotangents(sizes, device, 21)
    generator = torch.Generator().manual_seed(21)
    kept = []
    for _ in range(7):
        with torch.no_grad():  # new values in the same tensors: a replay must read them
            scene["means"] += 0.01 * torch.randn(scene["means"].shape, generator=generator).to(device)
            scene["colors"].copy_(torch.rand(scene["colors"].shape, generator=generator))
        exact = _exact(scene, sizes, cotangents)
        passed = render_and_grad(ops.rasterize_gaussians, scene, sizes, cotangents, densify=True)
        _assert_same_pass(exact, passed)
        if keep_outputs:  # the next call's buffers get other addresses: never the same key twice
            kept.append(passed)
        del exact, passed  # else the same allocations each time: the same addresses
    if not _is_cuda(device):
        assert pass_graphs.replays == pass_graphs.captures == 0 and pass_graphs.eager == 6
    elif keep_outputs:
        assert pass_graphs.captures == 0 and pass_graphs.eager == 6
    else:
        assert pass_graphs.captures >= 1 and pass_graphs.replays >= 2


def test_a_replayed_pass_still_raises_on_non_finite_inputs(device, pass_graphs):
    scene, sizes = make_scene(22, device=device, gaussian_count=200)
    cotangents = random_cotangents(sizes, device, 22)
    scene = {name: value.detach().requires_grad_(name in DIFFERENTIABLE) for name, value in scene.items()}
    for _ in range(5):
        render_and_grad(ops.rasterize_gaussians, scene, sizes, cotangents)
    replays = pass_graphs.replays
    with torch.no_grad():
        scene["opacities"].view(-1)[5] = float("nan")  # in place: the same addresses as the replayed calls
    with pytest.raises(ValueError, match="non-finite values in opacities"):
        render_and_grad(ops.rasterize_gaussians, scene, sizes, cotangents)
    if _is_cuda(device):
        assert pass_graphs.replays == replays + 1
