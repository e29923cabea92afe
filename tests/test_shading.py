"""The fused view-dependent colour kernel (ops.view_colors) against its plain-torch reference, per device."""

import pytest
import torch

from conftest import assert_matches_central_differences
from warpavatar import _torch_impl, ops

GAUSSIAN_COUNT = 3000


def make_inputs(seed: int, degree: int, device: str, *, count: int = GAUSSIAN_COUNT, dtype=torch.float32,
                extra_coefficients: int = 0):
    """Random posed Gaussians: non-unit quaternions, coefficients of either sign, an origin off-centre."""
    generator = torch.Generator().manual_seed(seed)

    def random(*shape, scale=1.0):
        return (scale * torch.randn(*shape, generator=generator, dtype=torch.float64)).to(device=device, dtype=dtype)

    return {
        "means": random(count, 3, scale=2.0),
        "quats": random(count, 4),  # lengths spread around 2: the kernel must not normalize them
        "canonical_quats": random(count, 4),
        "sh_coefficients": random(count, (degree + 1) ** 2 + extra_coefficients, 3, scale=0.6),
        "origin": random(3),
    }


def values_and_grads(function, inputs: dict, cotangent: torch.Tensor, degree: int):
    leaves = {name: value.detach().clone().requires_grad_() for name, value in inputs.items()}
    colors = function(*leaves.values(), sh_degree=degree)
    grads = torch.autograd.grad(colors, list(leaves.values()), cotangent, allow_unused=True)
    return colors.detach(), {name: grad for name, grad in zip(leaves, grads)}


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_matches_reference(device, degree):
    inputs = make_inputs(degree, degree, device)
    cotangent = torch.randn(GAUSSIAN_COUNT, 3, generator=torch.Generator().manual_seed(10 + degree)).to(device)
    colors, grads = values_and_grads(ops.view_colors, inputs, cotangent, degree)
    expected, expected_grads = values_and_grads(_torch_impl.view_colors, inputs, cotangent, degree)
    assert expected.std() > 0.1 and (expected == 0).any() and (expected > 0).any()  # the clamp is exercised
    torch.testing.assert_close(colors, expected, rtol=1e-5, atol=2e-6)
    for name, grad in grads.items():
        reference = expected_grads[name]
        if reference is None:  # degree 0: the direction is unused, its inputs get no gradient
            assert grad is None or not grad.any(), name
            continue
        assert reference.abs().max() > 1e-2, name
        torch.testing.assert_close(grad, reference, rtol=1e-4, atol=1e-5 * reference.abs().max().item(),
                                   msg=lambda message, n=name: f"d/d{n}: {message}")


def test_extra_coefficients_are_ignored(device):
    # an avatar rendered below its trained degree passes all its coefficients and a lower degree
    inputs = make_inputs(7, 1, device, count=500, extra_coefficients=5)
    cotangent = torch.randn(500, 3, generator=torch.Generator().manual_seed(8)).to(device)
    colors, grads = values_and_grads(ops.view_colors, inputs, cotangent, 1)
    expected, expected_grads = values_and_grads(_torch_impl.view_colors, inputs, cotangent, 1)
    torch.testing.assert_close(colors, expected, rtol=1e-5, atol=2e-6)
    torch.testing.assert_close(grads["sh_coefficients"], expected_grads["sh_coefficients"])
    assert not grads["sh_coefficients"][:, 4:].any() and grads["sh_coefficients"][:, :4].abs().max() > 1e-2


@pytest.mark.parametrize("degree", [1, 3])
def test_reference_gradients_match_central_differences(degree):
    # the reference's autograd in float64 against difference quotients, so the kernel is compared to a truth
    inputs = make_inputs(20 + degree, degree, "cpu", count=6, dtype=torch.float64)
    cotangent = torch.randn(6, 3, generator=torch.Generator().manual_seed(30), dtype=torch.float64)
    _, grads = values_and_grads(_torch_impl.view_colors, inputs, cotangent, degree)

    def objective(values):
        return (_torch_impl.view_colors(*values.values(), sh_degree=degree) * cotangent).sum()

    assert_matches_central_differences(objective, inputs, grads, epsilon=1e-6, rtol=1e-5, relative_atol=1e-6,
                                       min_scale=1e-2)


def test_kernel_gradients_match_central_differences_of_the_reference():
    # the kernel's hand-written backward against float64 difference quotients, directly
    degree, count = 3, 5
    inputs = make_inputs(40, degree, "cpu", count=count, dtype=torch.float64)
    cotangent = torch.randn(count, 3, generator=torch.Generator().manual_seed(41), dtype=torch.float64)
    _, grads = values_and_grads(ops.view_colors, {k: v.float() for k, v in inputs.items()}, cotangent.float(),
                                degree)

    def objective(values):
        return (_torch_impl.view_colors(*values.values(), sh_degree=degree) * cotangent).sum()

    assert_matches_central_differences(objective, inputs, grads, epsilon=1e-6, rtol=1e-3, relative_atol=1e-4,
                                       min_scale=1e-2)


def test_origin_gradient_and_empty_input(device):
    inputs = make_inputs(50, 2, device, count=200)
    cotangent = torch.randn(200, 3, generator=torch.Generator().manual_seed(51)).to(device)
    origin = inputs["origin"].clone().requires_grad_()
    colors = ops.view_colors(inputs["means"], inputs["quats"], inputs["canonical_quats"], inputs["sh_coefficients"],
                             origin)
    expected = _torch_impl.view_colors(inputs["means"], inputs["quats"], inputs["canonical_quats"],
                                       inputs["sh_coefficients"], origin)
    (grad,) = torch.autograd.grad(colors, origin, cotangent)
    (expected_grad,) = torch.autograd.grad(expected, origin, cotangent)
    torch.testing.assert_close(grad, expected_grad, rtol=1e-4, atol=1e-5 * expected_grad.abs().max().item())
    empty = {name: value[:0] if value.dim() > 1 else value for name, value in inputs.items()}
    assert ops.view_colors(*empty.values()).shape == (0, 3)


@pytest.mark.parametrize("change, message", [
    (lambda x: {**x, "quats": x["quats"][:, :3]}, "quats must have shape"),
    (lambda x: {**x, "origin": x["origin"].double()}, "origin must be float32"),
    (lambda x: {**x, "sh_coefficients": x["sh_coefficients"][:, :3]}, "not a square"),
])
def test_bad_inputs_are_named(change, message):
    inputs = change(make_inputs(60, 1, "cpu", count=10))
    with pytest.raises((ValueError, TypeError), match=message):
        ops.view_colors(*inputs.values())


def test_bench_kernels_shading_quick_runs(capsys):
    from conftest import load_tool

    assert load_tool("bench_kernels").main(["shading", "--quick", "--device", "cpu"]) == 0
    table = capsys.readouterr().out
    assert table.count("| warp fused |") == 2 and table.count("| torch op-by-op |") == 2
