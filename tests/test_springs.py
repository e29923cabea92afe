"""Tests of :func:`warpavatar.ops.spring_step`, ``isometry_loss`` and ``damping_loss``.

Values and gradients are compared with the plain-torch references on random graphs; a two-mass oscillator is
compared with its closed-form solution; the gradient of a 20-step rollout is compared with central finite
differences of the float64 reference rollout.
"""

import math

import pytest
import torch

from warpavatar import ops
from warpavatar._torch_impl import springs as reference

FLOAT_NAMES = ("x", "v", "rest_offset", "stiffness", "damping", "mass", "force")


def random_system(seed, *, node_count=40, edge_count=200, invalid_edges=10, sort_edges=False,
                  edge_dtype=torch.int32, dtype=torch.float32, device="cpu"):
    """Random spring graph; some edges carry out-of-range ids (they must be ignored)."""
    generator = torch.Generator().manual_seed(seed)

    def rand(*shape, low=-1.0, high=1.0):
        return low + (high - low) * torch.rand(*shape, generator=generator, dtype=torch.float64)

    edges = torch.randint(0, max(node_count, 1), (edge_count, 2), generator=generator)
    if sort_edges:
        edges = edges[edges[:, 0].argsort()]
    invalid_edges = min(invalid_edges, edge_count)
    if invalid_edges:
        rows = torch.randperm(edge_count, generator=generator)[:invalid_edges]
        bad_ids = torch.tensor([-1, node_count, node_count + 7, -5])
        edges[rows, torch.randint(0, 2, (invalid_edges,), generator=generator)] = bad_ids[
            torch.randint(0, 4, (invalid_edges,), generator=generator)
        ]
    system = dict(
        x=rand(node_count, 3),
        v=rand(node_count, 3),
        rest_offset=rand(edge_count, 3, low=-0.3, high=0.3),
        stiffness=rand(edge_count, low=0.5, high=3.0),
        damping=rand(node_count, low=0.1, high=1.0),
        mass=rand(node_count, low=0.5, high=2.0),
        force=rand(node_count, 3),
    )
    system = {name: value.to(dtype=dtype, device=device) for name, value in system.items()}
    system["edges"] = edges.to(dtype=edge_dtype, device=device)
    return system


def call_step(step, system, dt):
    return step(system["x"], system["v"], system["edges"], system["rest_offset"], system["stiffness"],
                system["damping"], system["mass"], system["force"], dt)


def leaf_copy(system, dtype=None):
    """The system with float tensors as fresh leaves that require grad (optionally cast)."""
    copy = dict(system)
    for name in FLOAT_NAMES:
        copy[name] = system[name].detach().to(dtype or system[name].dtype).clone().requires_grad_()
    return copy


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("sort_edges, edge_dtype", [(False, torch.int32), (True, torch.int64)])
def test_spring_step_matches_reference(device, seed, sort_edges, edge_dtype):
    system = random_system(seed, sort_edges=sort_edges, edge_dtype=edge_dtype, device=device)
    warp_inputs, torch_inputs = leaf_copy(system), leaf_copy(system)
    x_next, v_next = call_step(ops.spring_step, warp_inputs, 0.05)
    x_ref, v_ref = call_step(reference.spring_step, torch_inputs, 0.05)
    assert x_next.dtype == torch.float32 and x_next.device == x_ref.device
    torch.testing.assert_close(x_next, x_ref, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(v_next, v_ref, rtol=1e-5, atol=1e-6)

    generator = torch.Generator().manual_seed(100 + seed)
    cotangent_x = torch.randn(x_next.shape, generator=generator).to(device)
    cotangent_v = torch.randn(v_next.shape, generator=generator).to(device)
    grads = torch.autograd.grad((x_next, v_next), [warp_inputs[n] for n in FLOAT_NAMES], (cotangent_x, cotangent_v))
    grads_ref = torch.autograd.grad((x_ref, v_ref), [torch_inputs[n] for n in FLOAT_NAMES],
                                    (cotangent_x, cotangent_v))
    for name, grad, grad_ref in zip(FLOAT_NAMES, grads, grads_ref):
        torch.testing.assert_close(grad, grad_ref, rtol=1e-4, atol=1e-5, msg=lambda m, n=name: f"d/d{n}: {m}")
    # Ignored edges get exactly zero gradients.
    node_count = system["x"].shape[0]
    invalid = ((system["edges"] < 0) | (system["edges"] >= node_count)).any(dim=1)
    assert invalid.any()
    assert (grads[2][invalid] == 0).all() and (grads[3][invalid] == 0).all()


def test_partial_gradients(device):
    # Only some inputs require grad (the edge pass is skipped when none of x, rest, stiffness does).
    system = random_system(3, device=device)
    for wanted in (["force", "mass"], ["stiffness"], ["v", "damping"]):
        warp_inputs, torch_inputs = dict(system), dict(system)
        for name in wanted:
            warp_inputs[name] = system[name].clone().requires_grad_()
            torch_inputs[name] = system[name].clone().requires_grad_()
        x_next, v_next = call_step(ops.spring_step, warp_inputs, 0.1)
        x_ref, v_ref = call_step(reference.spring_step, torch_inputs, 0.1)
        loss, loss_ref = (x_next.sin() + v_next).sum(), (x_ref.sin() + v_ref).sum()
        grads = torch.autograd.grad(loss, [warp_inputs[n] for n in wanted])
        grads_ref = torch.autograd.grad(loss_ref, [torch_inputs[n] for n in wanted])
        for grad, grad_ref in zip(grads, grads_ref):
            torch.testing.assert_close(grad, grad_ref, rtol=1e-4, atol=1e-5)


def run_oscillator(dt, duration, device):
    """Two unit masses joined by a spring in both directions (rest offset 1 along x), damped, no force."""
    mass, stiffness, damping = 1.0, 2.0 * math.pi**2, 0.5
    x = torch.tensor([[1.2, 0.3, -0.1], [0.0, 0.3, -0.1]])
    v = torch.zeros(2, 3)
    edges = torch.tensor([[0, 1], [1, 0]], dtype=torch.int32)
    rest_offset = torch.tensor([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    args = (edges, rest_offset, torch.full((2,), stiffness), torch.full((2,), damping), torch.full((2,), mass),
            torch.zeros(2, 3))
    steps = round(duration / dt)
    x_ref, v_ref = x.double(), v.double()
    reference_args = tuple(a.double() if a.is_floating_point() else a for a in args)
    x, v, args = x.to(device), v.to(device), tuple(a.to(device) for a in args)
    with torch.no_grad():
        for _ in range(steps):
            x, v = ops.spring_step(x, v, *args, dt)
            x_ref, v_ref = reference.spring_step(x_ref, v_ref, *reference_args, dt)
    x = x.cpu()
    # Closed form: the stretch u = x0 - x1 - L obeys u'' = -(damping/m) u' - (2 stiffness/m) u, u(0) = 0.2,
    # u'(0) = 0, while the centre of mass stays at rest.
    beta = damping / (2.0 * mass)
    omega = math.sqrt(2.0 * stiffness / mass)
    omega_d = math.sqrt(omega**2 - beta**2)
    t = steps * dt
    stretch = 0.2 * math.exp(-beta * t) * (math.cos(omega_d * t) + beta / omega_d * math.sin(omega_d * t))
    return x, x_ref, stretch, omega


def test_two_mass_oscillator_closed_form(device):
    errors = []
    for dt in (1e-3, 5e-4):
        x, x_ref, stretch, omega = run_oscillator(dt, 1.3, device)
        # Float32 Warp against the float64 reference of the same scheme: round-off only (~2600 steps).
        torch.testing.assert_close(x.double(), x_ref, rtol=0.0, atol=2e-5)
        centre = x.double().mean(dim=0)
        torch.testing.assert_close(centre, torch.tensor([0.6, 0.3, -0.1], dtype=torch.float64), rtol=0, atol=1e-5)
        error = abs((x[0, 0] - x[1, 0]).item() - 1.0 - stretch)
        # Semi-implicit Euler is first order: after a fixed time the error is C * omega * dt * |u0|; the
        # measured C is about 0.46, we allow 1.
        assert error < omega * dt * 0.2, (dt, error)
        assert abs((x[0, 1] - x[1, 1]).item()) < 1e-6  # no motion across the spring
        errors.append(error)
    # ... and the error halves with the step (first-order convergence to the closed form).
    assert 1.6 < errors[0] / errors[1] < 2.4, errors


def rollout(step, system, dt, steps):
    x, v = system["x"], system["v"]
    for _ in range(steps):
        x, v = step(x, v, system["edges"], system["rest_offset"], system["stiffness"], system["damping"],
                    system["mass"], system["force"], dt)
    return x, v


def test_rollout_gradient_matches_finite_differences(device):
    # 20 steps of a tiny graph: Warp autograd through time against central differences of the float64
    # reference rollout, for every element of every float input.
    system = random_system(7, node_count=5, edge_count=12, invalid_edges=2, device="cpu", dtype=torch.float64)
    dt, steps = 0.05, 20
    generator = torch.Generator().manual_seed(8)
    cotangent_x = torch.randn(5, 3, generator=generator, dtype=torch.float64)
    cotangent_v = torch.randn(5, 3, generator=generator, dtype=torch.float64)

    def objective(values):
        x, v = rollout(reference.spring_step, values, dt, steps)
        return (x * cotangent_x).sum() + (v * cotangent_v).sum()

    warp_system = {name: (value.to(device) if name == "edges" else value.float().to(device))
                   for name, value in system.items()}
    warp_inputs = leaf_copy(warp_system)
    x, v = rollout(ops.spring_step, warp_inputs, dt, steps)
    loss = (x * cotangent_x.float().to(device)).sum() + (v * cotangent_v.float().to(device)).sum()
    grads = torch.autograd.grad(loss, [warp_inputs[n] for n in FLOAT_NAMES])

    epsilon = 1e-6
    for name, grad in zip(FLOAT_NAMES, grads):
        finite_difference = torch.zeros_like(system[name])
        flat = finite_difference.view(-1)
        for element in range(flat.numel()):
            plus, minus = dict(system), dict(system)
            plus[name] = system[name].clone()
            minus[name] = system[name].clone()
            plus[name].view(-1)[element] += epsilon
            minus[name].view(-1)[element] -= epsilon
            flat[element] = (objective(plus) - objective(minus)) / (2.0 * epsilon)
        scale = finite_difference.abs().max().item()
        assert scale > 1e-3, name  # every input matters
        # Float32 rollout: relative error ~1e-5 per step, amplified mildly over 20 steps.
        torch.testing.assert_close(grad.double().cpu(), finite_difference, rtol=0.0, atol=2e-4 * scale,
                                   msg=lambda m, n=name: f"d/d{n}: {m}")


def test_empty_edges_and_nodes(device):
    system = random_system(9, edge_count=0, invalid_edges=0, device=device)
    warp_inputs = leaf_copy(system)
    x_next, v_next = call_step(ops.spring_step, warp_inputs, 0.1)
    x_ref, v_ref = call_step(reference.spring_step, system, 0.1)
    torch.testing.assert_close(x_next, x_ref, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(v_next, v_ref, rtol=1e-5, atol=1e-6)
    grads = torch.autograd.grad((x_next.sum() + v_next.sum()), [warp_inputs[n] for n in FLOAT_NAMES])
    assert grads[2].shape == (0, 3) and grads[3].shape == (0,)
    torch.testing.assert_close(grads[0], torch.ones_like(grads[0]))

    empty = random_system(9, node_count=0, edge_count=0, invalid_edges=0, device=device)
    x_next, v_next = call_step(ops.spring_step, empty, 0.1)
    assert x_next.shape == (0, 3) and v_next.shape == (0, 3)
    # Edges that all point outside an empty node set are ignored too.
    empty["edges"] = torch.tensor([[0, 1]], dtype=torch.int32, device=device)
    empty["rest_offset"], empty["stiffness"] = torch.zeros(1, 3, device=device), torch.ones(1, device=device)
    assert call_step(ops.spring_step, empty, 0.1)[0].shape == (0, 3)


def test_spring_step_bad_input(device):
    system = random_system(10, node_count=6, edge_count=8, invalid_edges=2, device=device)

    def with_(**changes):
        return call_step(ops.spring_step, {**system, **changes}, changes.pop("dt", 0.1))

    with pytest.raises(ValueError, match=r"x must have shape \[\*, 3\]"):
        with_(x=system["x"][:, :2])
    with pytest.raises(ValueError, match=r"v must have shape \[6, 3\]"):
        with_(v=system["v"][:5])
    with pytest.raises(ValueError, match=r"edges must have shape \[\*, 2\]"):
        with_(edges=system["edges"][:, :1])
    with pytest.raises(TypeError, match="edges must be an integer tensor"):
        with_(edges=system["edges"].float())
    with pytest.raises(ValueError, match=r"rest_offset must have shape \[8, 3\]"):
        with_(rest_offset=system["rest_offset"][:7])
    with pytest.raises(ValueError, match=r"stiffness must have shape \[8\]"):
        with_(stiffness=system["stiffness"][:, None])
    with pytest.raises(ValueError, match=r"mass must have shape \[6\]"):
        with_(mass=system["mass"][:3])
    with pytest.raises(TypeError, match="damping must be float32"):
        with_(damping=system["damping"].double())
    with pytest.raises(TypeError, match="force must be a floating-point tensor"):
        with_(force=system["force"].int())
    with pytest.raises(ValueError, match="dt must be finite"):
        call_step(ops.spring_step, system, float("nan"))
    with pytest.raises(TypeError, match="dt must be a Python number"):
        call_step(ops.spring_step, system, torch.tensor(0.1))
    if device != "cpu":
        with pytest.raises(ValueError, match="is on cpu"):
            with_(force=system["force"].cpu())


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_isometry_loss_matches_reference(device, seed):
    system = random_system(seed, device=device)
    x = system["x"].clone().requires_grad_()
    rest = system["rest_offset"].clone().requires_grad_()
    x_ref = system["x"].clone().requires_grad_()
    rest_ref = system["rest_offset"].clone().requires_grad_()
    loss = ops.isometry_loss(x, system["edges"], rest)
    loss_ref = reference.isometry_loss(x_ref, system["edges"], rest_ref)
    assert loss.shape == () and loss.dtype == torch.float32
    torch.testing.assert_close(loss, loss_ref, rtol=1e-5, atol=1e-7)
    cotangent = torch.tensor(1.7, device=device)
    grads = torch.autograd.grad(loss, [x, rest], cotangent)
    grads_ref = torch.autograd.grad(loss_ref, [x_ref, rest_ref], cotangent)
    for grad, grad_ref in zip(grads, grads_ref):
        torch.testing.assert_close(grad, grad_ref, rtol=1e-4, atol=1e-6)


def test_isometry_loss_finite_differences(device):
    system = random_system(11, node_count=6, edge_count=10, invalid_edges=2, dtype=torch.float64)
    x = system["x"].float().to(device).requires_grad_()
    rest = system["rest_offset"].float().to(device).requires_grad_()
    edges = system["edges"].to(device)
    grad_x, grad_rest = torch.autograd.grad(ops.isometry_loss(x, edges, rest), [x, rest])
    epsilon = 1e-6
    for value, grad, is_x in ((system["x"], grad_x, True), (system["rest_offset"], grad_rest, False)):
        finite_difference = torch.zeros_like(value)
        for element in range(value.numel()):
            plus, minus = value.clone(), value.clone()
            plus.view(-1)[element] += epsilon
            minus.view(-1)[element] -= epsilon
            if is_x:
                delta = (reference.isometry_loss(plus, system["edges"], system["rest_offset"])
                         - reference.isometry_loss(minus, system["edges"], system["rest_offset"]))
            else:
                delta = (reference.isometry_loss(system["x"], system["edges"], plus)
                         - reference.isometry_loss(system["x"], system["edges"], minus))
            finite_difference.view(-1)[element] = delta / (2.0 * epsilon)
        torch.testing.assert_close(grad.double().cpu(), finite_difference, rtol=1e-4, atol=1e-6)


def test_isometry_loss_edge_cases(device):
    x = torch.randn(5, 3, device=device, requires_grad=True)
    no_edges = ops.isometry_loss(
        x, torch.zeros(0, 2, dtype=torch.int64, device=device), torch.zeros(0, 3, device=device)
    )
    assert no_edges.item() == 0.0
    assert (torch.autograd.grad(no_edges, x)[0] == 0).all()
    # Only padding edges: no valid edge either.
    padding = torch.tensor([[0, -1], [-1, 2]], device=device)
    assert ops.isometry_loss(x, padding, torch.ones(2, 3, device=device)).item() == 0.0
    # Coincident endpoints and zero rest offsets: finite value, zero gradient through the undefined direction.
    points = torch.zeros(2, 3, device=device, requires_grad=True)
    rest = torch.zeros(1, 3, device=device, requires_grad=True)
    edges = torch.tensor([[0, 1]], dtype=torch.int32, device=device)
    loss = ops.isometry_loss(points, edges, rest)
    grads = torch.autograd.grad(loss, [points, rest])
    assert loss.item() == 0.0 and all((g == 0).all() for g in grads)
    with pytest.raises(ValueError, match=r"rest_offset must have shape \[1, 3\]"):
        ops.isometry_loss(points, edges, torch.zeros(2, 3, device=device))
    with pytest.raises(TypeError, match="x must be float32"):
        ops.isometry_loss(points.double(), edges, rest)


@pytest.mark.parametrize("shape", [(50, 3), (4, 30, 3)])
def test_damping_loss_matches_reference(device, shape):
    for seed in (0, 1):
        generator = torch.Generator().manual_seed(seed)
        velocity = torch.randn(shape, generator=generator).to(device).requires_grad_()
        velocity_ref = velocity.detach().clone().requires_grad_()
        loss, loss_ref = ops.damping_loss(velocity), reference.damping_loss(velocity_ref)
        torch.testing.assert_close(loss, loss_ref, rtol=1e-5, atol=1e-7)
        cotangent = torch.tensor(0.3, device=device)
        grad, = torch.autograd.grad(loss, velocity, cotangent)
        grad_ref, = torch.autograd.grad(loss_ref, velocity_ref, cotangent)
        assert grad.shape == velocity.shape
        torch.testing.assert_close(grad, grad_ref, rtol=1e-5, atol=1e-7)
    # Non-contiguous input and empty input.
    velocity = torch.randn(3, 10, device=device).t()[:, :3]
    torch.testing.assert_close(ops.damping_loss(velocity.contiguous()), ops.damping_loss(velocity))
    assert ops.damping_loss(torch.zeros(0, 3, device=device)).item() == 0.0
    with pytest.raises(ValueError, match=r"\[\.\.\., 3\]"):
        ops.damping_loss(torch.zeros(4, 2, device=device))
    with pytest.raises(TypeError, match="velocity must be float32"):
        ops.damping_loss(torch.zeros(4, 3, dtype=torch.float64, device=device))


def test_training_rollout_with_regularizers(device):
    # The training pattern: roll out, regularize every state, backpropagate through time.
    system = random_system(12, node_count=30, edge_count=120, device=device)
    warp_inputs, torch_inputs = leaf_copy(system), leaf_copy(system)
    losses = []
    for step, inputs in ((ops.spring_step, warp_inputs), (reference.spring_step, torch_inputs)):
        iso, damp = (ops.isometry_loss, ops.damping_loss) if step is ops.spring_step else (
            reference.isometry_loss, reference.damping_loss)
        x, v, total = inputs["x"], inputs["v"], 0.0
        for _ in range(8):
            x, v = step(x, v, inputs["edges"], inputs["rest_offset"], inputs["stiffness"], inputs["damping"],
                        inputs["mass"], inputs["force"], 0.05)
            total = total + 0.1 * iso(x, inputs["edges"], inputs["rest_offset"]) + 0.01 * damp(v)
        losses.append(total)
    torch.testing.assert_close(losses[0], losses[1], rtol=1e-5, atol=1e-6)
    grads = torch.autograd.grad(losses[0], [warp_inputs[n] for n in FLOAT_NAMES])
    grads_ref = torch.autograd.grad(losses[1], [torch_inputs[n] for n in FLOAT_NAMES])
    for name, grad, grad_ref in zip(FLOAT_NAMES, grads, grads_ref):
        torch.testing.assert_close(grad, grad_ref, rtol=1e-4, atol=1e-5, msg=lambda m, n=name: f"d/d{n}: {m}")
