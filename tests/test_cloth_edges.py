"""Tests of :func:`warpavatar.ops.cloth_edge_terms` against its plain-torch reference and finite differences."""

import pytest
import torch

from conftest import assert_matches_central_differences
from warpavatar import ops
from warpavatar._torch_impl import cloth as reference

NAMES = ("x", "v", "rest_length", "edge_damping")


def random_edges(seed, *, node_count=50, edge_count=300, invalid=12, device="cpu", dtype=torch.float32):
    """Random directed edges (some padding ids), rest lengths from half to three times the current lengths, so
    both sides of the clamp ``min(L, 2|d|)`` occur."""
    generator = torch.Generator().manual_seed(seed)
    x = torch.rand(node_count, 3, generator=generator, dtype=torch.float64)
    edges = torch.randint(0, node_count, (edge_count, 2), generator=generator)
    edges = edges[edges[:, 0] != edges[:, 1]]
    rows = torch.randperm(edges.shape[0], generator=generator)[:invalid]
    edges[rows, torch.randint(0, 2, (len(rows),), generator=generator)] = torch.tensor([-1, node_count])[
        torch.randint(0, 2, (len(rows),), generator=generator)]
    length = (x[edges[:, 0].clamp(0, node_count - 1)] - x[edges[:, 1].clamp(0, node_count - 1)]).norm(dim=1)
    system = {
        "x": x,
        "v": torch.randn(node_count, 3, generator=generator, dtype=torch.float64),
        "rest_length": length * (0.5 + 2.5 * torch.rand(len(edges), generator=generator, dtype=torch.float64)),
        "edge_damping": 0.1 + torch.rand(len(edges), generator=generator, dtype=torch.float64),
    }
    system = {name: value.to(device=device, dtype=dtype) for name, value in system.items()}
    system["edges"] = edges.to(device=device, dtype=torch.int32)
    return system


def leaves(system, dtype=None):
    return {**system, **{n: system[n].detach().to(dtype or system[n].dtype).clone().requires_grad_() for n in NAMES}}


def call(op, system):
    return op(system["x"], system["v"], system["edges"], system["rest_length"], system["edge_damping"])


def clamp_margin(system):
    """Per edge, |L - 2|d|| relative to L (float64): how far from the clamp's kink."""
    x, edges = system["x"].double().cpu(), system["edges"].long().cpu().clamp(0, system["x"].shape[0] - 1)
    length = (x[edges[:, 0]] - x[edges[:, 1]]).norm(dim=1)
    rest = system["rest_length"].double().cpu()
    return (rest - 2 * length).abs() / rest


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_matches_reference(device, seed):
    system = random_edges(seed, device=device)
    ours, theirs = leaves(system), leaves(system)
    outputs, outputs_ref = call(ops.cloth_edge_terms, ours), call(reference.cloth_edge_terms, theirs)
    for output, output_ref in zip(outputs, outputs_ref):
        assert output.dtype == torch.float32 and output.device == output_ref.device
        torch.testing.assert_close(output, output_ref, rtol=1e-5, atol=1e-6)
    # both sides of the clamp occur, padding edges give nothing
    x, edges = system["x"], system["edges"].long()
    valid = ((edges >= 0) & (edges < x.shape[0])).all(dim=1)
    lengths = (x[edges[valid, 0]] - x[edges[valid, 1]]).norm(dim=1)
    clamped = system["rest_length"][valid] >= 2 * lengths
    assert 10 < clamped.sum() < valid.sum() - 10
    assert (outputs[0][~valid] == 0).all()
    generator = torch.Generator().manual_seed(seed + 20)
    cotangents = [torch.randn(output.shape, generator=generator).to(device) for output in outputs]
    grads = torch.autograd.grad(outputs, [ours[n] for n in NAMES], cotangents)
    grads_ref = torch.autograd.grad(outputs_ref, [theirs[n] for n in NAMES], cotangents)
    for name, grad, grad_ref in zip(NAMES, grads, grads_ref):
        assert grad.abs().max() > 0, name
        torch.testing.assert_close(grad, grad_ref, rtol=1e-4, atol=1e-5, msg=lambda m, n=name: f"d/d{n}: {m}")
    assert (grads[2][~valid] == 0).all() and (grads[3][~valid] == 0).all()


def test_offsets_make_spring_step_an_exact_length_spring(device):
    system = random_edges(3, invalid=0, device=device)
    rest_offset, _ = call(ops.cloth_edge_terms, system)
    x, edges = system["x"], system["edges"].long()
    delta = x[edges[:, 0]] - x[edges[:, 1]]
    length = delta.norm(dim=1, keepdim=True)
    effective = torch.minimum(system["rest_length"][:, None], 2 * length)
    # the spring term k (d - offset) is k (|d| - L') along d
    torch.testing.assert_close(delta - rest_offset, (length - effective) * delta / length, rtol=1e-5, atol=1e-6)


def test_finite_differences(device):
    system = random_edges(4, node_count=8, edge_count=24, invalid=3, dtype=torch.float64)
    keep = clamp_margin(system) > 1e-3  # away from the clamp's kink
    for name in ("edges", "rest_length", "edge_damping"):
        system[name] = system[name][keep]
    ours = leaves({n: (v.to(device) if n == "edges" else v.float().to(device)) for n, v in system.items()})
    outputs = call(ops.cloth_edge_terms, ours)
    generator = torch.Generator().manual_seed(5)
    cotangents = [torch.randn(output.shape, generator=generator, dtype=torch.float64) for output in outputs]
    grads = torch.autograd.grad(outputs, [ours[n] for n in NAMES], [c.float().to(device) for c in cotangents])

    def objective(values):
        return sum((output * c).sum() for output, c in zip(call(reference.cloth_edge_terms, values), cotangents))

    assert_matches_central_differences(objective, system, dict(zip(NAMES, grads)), epsilon=1e-7, rtol=1e-3,
                                       relative_atol=1e-4, min_scale=1e-2)


def test_degenerate_and_empty(device):
    # coincident endpoints: no direction, zero offset and finite gradients
    x = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [1.0, 0.0, 0.0]], device=device, requires_grad=True)
    v = torch.randn(3, 3, device=device, requires_grad=True)
    edges = torch.tensor([[0, 1], [1, 2]], device=device)
    rest = torch.tensor([0.5, 0.5], device=device, requires_grad=True)
    damping = torch.tensor([1.0, 2.0], device=device, requires_grad=True)
    offset, force = ops.cloth_edge_terms(x, v, edges, rest, damping)
    assert (offset[0] == 0).all()
    torch.testing.assert_close(offset[1], torch.tensor([-0.5, 0.0, 0.0], device=device))
    grads = torch.autograd.grad(offset.sum() + force.sum(), [x, v, rest, damping])
    assert all(torch.isfinite(g).all() for g in grads)
    # no edges, and no nodes
    no_edges = ops.cloth_edge_terms(x, v, edges[:0], rest[:0], damping[:0])
    assert no_edges[0].shape == (0, 3) and (no_edges[1] == 0).all()
    grads = torch.autograd.grad(no_edges[1].sum(), [x, v])
    assert all((g == 0).all() for g in grads)
    empty = ops.cloth_edge_terms(x[:0], v[:0], edges, rest, damping)
    assert empty[0].shape == (2, 3) and (empty[0] == 0).all() and empty[1].shape == (0, 3)


def test_bad_input(device):
    system = random_edges(6, node_count=6, edge_count=10, invalid=2, device=device)

    def with_(**changes):
        return call(ops.cloth_edge_terms, {**system, **changes})

    with pytest.raises(ValueError, match=r"v must have shape \[6, 3\]"):
        with_(v=system["v"][:5])
    with pytest.raises(ValueError, match=r"edges must have shape \[\*, 2\]"):
        with_(edges=system["edges"][:, :1])
    with pytest.raises(TypeError, match="edges must be an integer tensor"):
        with_(edges=system["edges"].float())
    edge_count = system["edges"].shape[0]
    with pytest.raises(ValueError, match=rf"rest_length must have shape \[{edge_count}\]"):
        with_(rest_length=system["rest_length"][:-1])
    with pytest.raises(TypeError, match="edge_damping must be float32"):
        with_(edge_damping=system["edge_damping"].double())
    if device != "cpu":
        with pytest.raises(ValueError, match="is on cpu"):
            with_(v=system["v"].cpu())
