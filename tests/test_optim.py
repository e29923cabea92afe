"""``warpavatar.optim``: Adam without torch.optim's machinery, held to ``torch.optim.Adam(fused=True)`` bit for bit,
its state dicts interchangeable with torch's, and no ``torch._dynamo`` import."""

import subprocess
import sys

import pytest
import torch

from warpavatar.optim import Adam


def _problem(device, seed):
    """Two parameter groups (one with its own learning rate, a name and a tensor learning rate), random values."""
    generator = torch.Generator().manual_seed(seed)
    shapes = [(7, 3), (5,), (4, 2, 3)]
    values = [torch.randn(*shape, generator=generator).to(device) for shape in shapes]
    grads = [[torch.randn(*shape, generator=generator).to(device) for shape in shapes] for _ in range(6)]
    return values, grads


def _groups(parameters, device, *, tensor_lr):
    first_lr = torch.tensor(0.03, device=device) if tensor_lr else 0.03
    return [{"params": parameters[:2], "lr": first_lr, "name": "first"},
            {"params": parameters[2:], "eps": 1e-15, "weight_decay": 0.01}]


def _run(optimizer_type, values, grads, device, *, tensor_lr=False, start=0, stop=None, state=None, **options):
    parameters = [value.clone().requires_grad_() for value in values]
    optimizer = optimizer_type(_groups(parameters, device, tensor_lr=tensor_lr), lr=0.01, betas=(0.8, 0.95),
                               **options)
    if state is not None:
        optimizer.load_state_dict(state)
    for step_grads in grads[start:stop]:
        for parameter, grad in zip(parameters, step_grads):
            parameter.grad = grad.clone()
        optimizer.step()
        optimizer.zero_grad()
    return parameters, optimizer


def _torch_adam(groups, **options):
    return torch.optim.Adam(groups, fused=True, **options)


@pytest.mark.parametrize("tensor_lr", [False, True], ids=["float_lr", "tensor_lr"])
def test_adam_matches_torch_fused_adam_bit_for_bit(device, tensor_lr):
    values, grads = _problem(device, 1)
    ours, our_optimizer = _run(Adam, values, grads, device, tensor_lr=tensor_lr)
    theirs, their_optimizer = _run(_torch_adam, values, grads, device, tensor_lr=tensor_lr)
    for a, b, value in zip(ours, theirs, values):
        assert not torch.equal(a, value) and torch.equal(a, b)
    for a, b in zip(ours, theirs):
        for key in ("step", "exp_avg", "exp_avg_sq"):
            assert torch.equal(our_optimizer.state[a][key], their_optimizer.state[b][key]), key
        assert our_optimizer.state[a]["step"].device == a.device


def test_state_dicts_resume_exactly_and_load_across_implementations(device):
    values, grads = _problem(device, 2)
    straight, _ = _run(Adam, values, grads, device)
    _, first_half = _run(Adam, values, grads, device, stop=3)
    saved = first_half.state_dict()
    assert [group["params"] for group in saved["param_groups"]] == [[0, 1], [2]]
    assert saved["param_groups"][0]["name"] == "first" and saved["param_groups"][1]["eps"] == 1e-15
    # the halves' parameters are not carried over by the state dict: start the second half from the first's values
    resumed_values = [parameter.detach() for parameter in _run(Adam, values, grads, device, stop=3)[0]]
    resumed, _ = _run(Adam, resumed_values, grads, device, start=3, state=saved)
    for a, b in zip(straight, resumed):
        assert torch.equal(a, b)
    # torch's state dict into ours, and ours into torch's: the same continuation as torch alone
    _, their_half = _run(_torch_adam, values, grads, device, stop=3)
    theirs_all, _ = _run(_torch_adam, values, grads, device)
    from_theirs, _ = _run(Adam, resumed_values, grads, device, start=3, state=their_half.state_dict())
    into_theirs, _ = _run(_torch_adam, resumed_values, grads, device, start=3, state=saved)
    for a, b, c in zip(theirs_all, from_theirs, into_theirs):
        assert torch.equal(a, b) and torch.equal(a, c)


def test_zero_grad_keeps_or_drops_the_gradients(device):
    parameters = [torch.randn(3, device=device, requires_grad=True) for _ in range(2)]
    optimizer = Adam(parameters, lr=0.1)
    for parameter in parameters:
        parameter.grad = torch.rand(3, device=device) + 1.0
    kept = [parameter.grad for parameter in parameters]
    optimizer.zero_grad(set_to_none=False)
    assert all(parameter.grad is grad and not grad.any() for parameter, grad in zip(parameters, kept))
    optimizer.zero_grad()
    assert all(parameter.grad is None for parameter in parameters)


def test_a_found_inf_flag_skips_the_step_as_torch_does(device):
    values, grads = _problem(device, 3)
    results = []
    for optimizer_type in (Adam, _torch_adam):
        parameters = [value.clone().requires_grad_() for value in values]
        optimizer = optimizer_type(parameters, lr=0.05)
        for flag, step_grads in zip((0.0, 1.0, 0.0), grads):
            optimizer.found_inf = torch.tensor(flag, device=device)
            for parameter, grad in zip(parameters, step_grads):
                parameter.grad = grad.clone()
            optimizer.step()
        results.append((parameters, [optimizer.state[parameter]["step"] for parameter in parameters]))
    (ours, our_steps), (theirs, their_steps) = results
    assert all(torch.equal(a, b) for a, b in zip(ours, theirs))
    assert all(float(step) == 2.0 for step in our_steps + their_steps)


def test_bad_options_and_inputs_are_clear_errors(device):
    parameter = torch.zeros(3, device=device, requires_grad=True)
    for bad, match in ((dict(lr=-1.0), "lr"), (dict(eps=-1.0), "eps"), (dict(betas=(0.9, 1.0)), "betas"),
                       (dict(weight_decay=-0.1), "weight_decay")):
        with pytest.raises(ValueError, match=match):
            Adam([parameter], **bad)
    with pytest.raises(ValueError, match="no parameters"):
        Adam([], lr=0.1)
    with pytest.raises(ValueError, match="more than one group"):
        Adam([{"params": [parameter]}, {"params": [parameter]}], lr=0.1)
    optimizer = Adam([parameter], lr=0.1)
    with pytest.raises(ValueError, match="other parameter groups"):
        optimizer.load_state_dict({"state": {}, "param_groups": [{"params": [0, 1]}]})
    index = torch.tensor([[0, 2]], device=device)
    parameter.grad = torch.sparse_coo_tensor(index, torch.ones(2, device=device), (3,), check_invariants=True)
    with pytest.raises(RuntimeError, match="sparse"):
        optimizer.step()


def test_adam_imports_no_dynamo():
    code = ("import sys, torch\n"
            "from warpavatar.optim import Adam\n"
            "p = torch.randn(4, requires_grad=True)\n"
            "o = Adam([p], lr=0.1)\n"
            "p.grad = torch.ones(4)\n"
            "o.step(); o.zero_grad(); o.load_state_dict(o.state_dict())\n"
            "assert 'torch._dynamo' not in sys.modules, 'torch._dynamo was imported'\n")
    subprocess.run([sys.executable, "-c", code], check=True)
