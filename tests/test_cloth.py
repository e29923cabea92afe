"""Physics sanity of :class:`warpavatar.sim.ClothModel`: a pinned chain's analytic sag, energy decay, collision,
attachments, stability at extreme parameters, determinism, and rollout gradients against finite differences."""

import copy
import math

import pytest
import torch

from warpavatar import ops
from warpavatar._torch_impl import cloth as reference_cloth
from warpavatar._torch_impl import collision as reference_collision
from warpavatar._torch_impl import springs as reference_springs
from warpavatar.sim import Capsules, ClothGraph, ClothModel, ClothState, cloth_graph
from warpavatar.sim.mass_spring_cloth import REST_LENGTH_RANGE

G = 9.81


def sheet(rows, columns, spacing, *, horizontal=False, device="cpu"):
    """A grid of nodes: vertical (x along a row, hanging down -z) or horizontal (in the x-y plane at z = 0)."""
    i, j = torch.meshgrid(torch.arange(rows), torch.arange(columns), indexing="ij")
    across, down = j.reshape(-1).float() * spacing, i.reshape(-1).float() * spacing
    zeros = torch.zeros_like(across)
    points = torch.stack([across, down, zeros] if horizontal else [across, zeros, -down], dim=1)
    return points.to(device)


def hanging_sheet(device, *, rows=6, columns=6, **options):
    rest = sheet(rows, columns, 0.04, device=device)
    attached = torch.arange(columns, device=device)  # the top row
    model = ClothModel(rest, cloth_graph(rest, neighbours=8, bend_per_node=6), attached, node_mass=0.01, **options)
    return model, rest


def with_fraction(parameter: torch.nn.Parameter, fraction):
    with torch.no_grad():
        parameter.copy_(torch.logit(torch.as_tensor(fraction, dtype=parameter.dtype)).expand_as(parameter))


def test_graph_is_symmetric_with_a_capped_second_ring(device):
    rest = sheet(7, 7, 0.05, device=device)
    graph = cloth_graph(rest, neighbours=4, bend_per_node=4)
    stretch = {tuple(p) for p in graph.stretch.tolist()}
    bend = {tuple(p) for p in graph.bend.tolist()}
    assert all(i < j for i, j in stretch | bend) and not stretch & bend
    index, _ = ops.knn_graph(rest, 4)
    # every k-NN pair is a stretch edge, in one direction only
    expected = {(min(i, j), max(i, j)) for i in range(49) for j in index[i].tolist()}
    assert stretch == expected and len(graph.stretch) == len(stretch)
    # bend edges join nodes two stretch steps apart
    neighbours = {i: set() for i in range(49)}
    for i, j in stretch:
        neighbours[i].add(j)
        neighbours[j].add(i)
    assert bend and all(neighbours[i] & neighbours[j] for i, j in bend)
    assert len(bend) <= 4 * 49
    assert cloth_graph(rest, neighbours=4, bend_per_node=0).bend.shape == (0, 2)


def test_pinned_chain_reaches_its_analytic_sag(device):
    count, spacing, mass = 6, 0.1, 0.01
    rest = torch.stack([torch.zeros(count), torch.zeros(count), -spacing * torch.arange(count).float()], 1)
    rest = rest.to(device)
    pairs = torch.stack([torch.arange(count - 1), torch.arange(1, count)], 1)
    graph = ClothGraph(pairs, pairs[:0])
    model = ClothModel(rest, graph, torch.tensor([0]), node_mass=mass).to(device)
    with_fraction(model.stiffness_logit, 0.5)
    with_fraction(model.drag_logit, 0.2)
    with_fraction(model.damping_logit, 0.5)
    state, frames = model.settle(model.rest_state(rest), rest[:1], max_frames=400, kinetic_tolerance=1e-9,
                                 extra_drag=0.0)
    assert frames < 400
    lengths = (state.positions[1:] - state.positions[:-1]).norm(dim=1).cpu()
    stiffness = model.stiffness().detach().cpu()
    weight_below = mass * G * torch.arange(count - 1, 0, -1).float()
    extension = weight_below / stiffness
    assert extension.min() > 0.003  # a visible sag (3 % of the spacing at the bottom)
    torch.testing.assert_close(lengths - spacing, extension, rtol=1e-3, atol=0.0)
    # the chain hangs straight down from its pin
    assert (state.positions[:, :2].abs() < 1e-5).all()


def soft_chain(device, **options):
    """A chain of 8 nodes 0.1 apart pinned at its top, its springs at 2 % of their stiffness bound."""
    count = 8
    rest = torch.stack([torch.zeros(count), torch.zeros(count), -0.1 * torch.arange(count).float()], 1).to(device)
    pairs = torch.stack([torch.arange(count - 1), torch.arange(1, count)], 1)
    model = ClothModel(rest, ClothGraph(pairs, pairs[:0]), torch.tensor([0]), node_mass=0.01, **options).to(device)
    with_fraction(model.stiffness_logit, 0.02)
    with_fraction(model.drag_logit, 0.2)
    with_fraction(model.damping_logit, 0.5)
    return model, rest


@pytest.mark.parametrize("fused", [True, False])
def test_strain_limiting_keeps_a_soft_chain_near_its_length(device, fused):
    ratios = {}
    for limit in (0.0, 1.05):
        model, rest = soft_chain(device, strain_limit=limit, strain_iterations=8)
        state = model.rest_state(rest)
        with torch.no_grad():
            for _ in range(60):  # 2 s hanging, no extra drag
                state = model.step(state, rest[:1], 1 / 30, fused=fused)
        lengths = (state.positions[1:] - state.positions[:-1]).norm(dim=1)
        ratios[limit] = float(lengths.max() / 0.1)
        assert torch.isfinite(state.positions).all()
        assert (state.positions[:, :2].abs() < 1e-4).all()  # still straight down from its pin
    assert ratios[0.0] > 1.3  # the soft springs alone stretch the top edge by more than 30 %
    assert ratios[1.05] < 1.05 + 0.01  # limited: within the limit, up to what 8 Jacobi passes leave


def test_strain_limiting_leaves_a_cloth_within_its_limit_alone(device):
    model, rest = soft_chain(device, strain_limit=1.5)
    reference, _ = soft_chain(device)
    state = model.rest_state(rest)
    with torch.no_grad():
        limited = model.step(state, rest[:1], 1 / 30, fused=False)
        free = reference.step(state, rest[:1], 1 / 30, fused=False)
    assert torch.equal(limited.positions, free.positions) and torch.equal(limited.velocities, free.velocities)


def test_strain_limited_rollout_gradients_match_finite_differences(monkeypatch):
    # the op-by-op step in float64 with the ops' torch references, through the strain limit's passes
    monkeypatch.setattr(ops, "spring_step", reference_springs.spring_step)
    monkeypatch.setattr(ops, "cloth_edge_terms", reference_cloth.cloth_edge_terms)
    model, rest = soft_chain("cpu", strain_limit=1.05, strain_iterations=3)
    model = model.double()
    generator = torch.Generator().manual_seed(3)
    with torch.no_grad():
        model.rest_length_logit.copy_(0.3 * torch.randn(model.rest_length_logit.shape, generator=generator))
    x0 = (rest.double() + 0.01 * torch.randn(rest.shape, generator=generator, dtype=torch.float64))
    x0[1:, 2] -= 0.01 * torch.arange(1, rest.shape[0], dtype=torch.float64) ** 2  # stretched past the limit
    weights = torch.randn(rest.shape, generator=generator, dtype=torch.float64)

    def loss(x0):
        state = ClothState(x0, torch.zeros_like(x0))
        for _ in range(3):
            state = model.step(state, x0[:1], 1 / 60, fused=False)
        return (weights * state.positions).sum()

    leaf = x0.clone().requires_grad_()
    analytic = torch.autograd.grad(loss(leaf), [leaf, model.rest_length_logit])
    epsilon = 1e-6
    with torch.no_grad():
        for value, grad in zip((x0, model.rest_length_logit), analytic):
            for element in range(value.numel()):
                original = value.view(-1)[element].item()
                value.view(-1)[element] = original + epsilon
                plus = loss(x0).item()
                value.view(-1)[element] = original - epsilon
                minus = loss(x0).item()
                value.view(-1)[element] = original
                numeric = (plus - minus) / (2 * epsilon)
                assert abs(grad.view(-1)[element].item() - numeric) <= 1e-5 * (1 + abs(numeric)), (element, numeric)
    assert analytic[1].abs().max() > 1e-2  # the rest lengths matter only through the limit here (soft springs)
    # the passes acted: without them the rollout differs
    with torch.no_grad():
        limited = loss(x0).item()
        model.strain_iterations = 0
        assert abs(loss(x0).item() - limited) > 1e-3


def test_energy_decays_with_damping(device):
    rest = sheet(6, 6, 0.04, horizontal=True, device=device)
    energies = {}
    for fraction in (1e-4, 0.3):
        model = ClothModel(rest, cloth_graph(rest, neighbours=8, bend_per_node=6), torch.arange(6),
                           node_mass=0.01).to(device)
        with_fraction(model.damping_logit, fraction)
        with_fraction(model.drag_logit, fraction)
        state = model.rest_state(rest)  # released horizontally, held along one edge: it swings down
        trace = []
        with torch.no_grad():
            for _ in range(60):
                state = model.step(state, rest[:6], 1 / 30)
                trace.append(model.energy(state).item())
        energies[fraction] = trace
    damped, free = energies[0.3], energies[1e-4]
    dissipated = damped[0] - damped[-1]
    assert dissipated > 0
    # monotone up to the explicit step's small energy oscillation
    rises = [max(0.0, b - a) for a, b in zip(damped, damped[1:])]
    assert max(rises) < 0.02 * dissipated
    # with (almost) no damping much less energy is lost over the same time
    assert free[0] - min(free[-10:]) < 0.5 * dissipated


def test_nothing_stays_inside_a_capsule_after_a_drop(device):
    rest = sheet(8, 8, 0.03, horizontal=True, device=device) + torch.tensor([-0.105, -0.105, 0.15], device=device)
    model = ClothModel(rest, cloth_graph(rest, neighbours=8, bend_per_node=6), torch.zeros(0, dtype=torch.long),
                       node_mass=0.01).to(device)
    capsules = Capsules(torch.tensor([[-0.3, 0.0, 0.0]], device=device), torch.tensor([[0.3, 0.0, 0.0]], device=device),
                        torch.tensor([0.08], device=device))
    state = model.rest_state(rest)
    no_targets = torch.zeros(0, 3, device=device)
    touched = False
    with torch.no_grad():
        for _ in range(40):
            before = state.positions
            state = model.step(state, no_targets, 1 / 30, capsules=capsules)
            x = state.positions
            distance = (x[:, 1:] ** 2).sum(dim=1).sqrt()  # to the capsule's axis (x within the segment)
            assert (distance >= 0.08 * (1 - 1e-5)).all()
            touched = touched or bool((distance < 0.0801).any())
            # no node tunnels through: one that stays over the capsule's width keeps its side of the axis (a
            # sheet centred on a frictionless capsule may slide off sideways: a tiny asymmetry, such as the
            # order of a GPU's atomic sums, decides which way)
            over = (before[:, 1].abs() < 0.07) & (x[:, 1].abs() < 0.07)
            assert torch.equal(torch.sign(before[over, 2]), torch.sign(x[over, 2]))
    assert touched
    assert torch.isfinite(state.positions).all() and torch.isfinite(state.velocities).all()


def test_a_capsule_moving_during_the_frame_lifts_the_cloth(device):
    # A capsule rises from below a free sheet into it within one frame: with the previous frame's capsule
    # given, it sweeps through the substeps and the sheet leaves with it, moving up; without, it appears at
    # its end position and the sheet is pushed out only at the last substep.
    rest = sheet(6, 6, 0.03, horizontal=True, device=device) + torch.tensor([-0.075, -0.075, 0.0], device=device)
    model = ClothModel(rest, cloth_graph(rest, neighbours=8, bend_per_node=4), torch.zeros(0, dtype=torch.long),
                       node_mass=0.01).to(device)

    def capsule(height):
        return Capsules(torch.tensor([[-0.3, 0.0, height]], device=device),
                        torch.tensor([[0.3, 0.0, height]], device=device), torch.tensor([0.05], device=device))

    no_targets = torch.zeros(0, 3, device=device)
    with torch.no_grad():
        swept = model.step(model.rest_state(rest), no_targets, 1 / 30, capsules=capsule(0.02),
                           previous_capsules=capsule(-0.1))
        jumped = model.step(model.rest_state(rest), no_targets, 1 / 30, capsules=capsule(0.02))
    for state in (swept, jumped):
        distance = (state.positions[:, 1:] - torch.tensor([0.0, 0.02], device=device)).norm(dim=1)
        assert (distance >= 0.05 * (1 - 1e-5)).all()
    # the nodes over the capsule ride up on it in the swept frame, at a good part of its speed (3.6 m/s); a
    # capsule that appears around them instead pushes them out below its axis, where they were
    lifted = swept.positions[:, 2] > 0.04
    assert lifted.sum() >= 6
    assert swept.velocities[lifted, 2].mean() > 1.5
    assert jumped.positions[:, 2].max() < 0.01


def test_attached_nodes_follow_their_targets_exactly(device):
    model, rest = hanging_sheet(device)
    model = model.to(device)
    state = model.rest_state(rest)
    top = rest[:6]
    with torch.no_grad():
        for frame in range(1, 8):
            angle = 0.2 * frame
            rotation = torch.tensor([[math.cos(angle), -math.sin(angle), 0.0], [math.sin(angle), math.cos(angle), 0.0],
                                     [0.0, 0.0, 1.0]], device=device)
            target = top @ rotation.T + torch.tensor([0.03 * frame, 0.0, 0.01 * frame], device=device)
            previous = state.positions[:6].clone()
            state = model.step(state, target, 1 / 30)
            assert torch.equal(state.positions[:6], target)
            torch.testing.assert_close(state.velocities[:6], (target - previous) * 30, rtol=1e-5, atol=1e-6)
    with pytest.raises(ValueError, match=r"attachment_targets must have shape \[6, 3\]"):
        model.step(state, target[:5], 1 / 30)
    with pytest.raises(ValueError, match="frame_interval must be > 0"):
        model.step(state, target, 0.0)


@pytest.mark.parametrize("logit", [50.0, -50.0, "mixed"])
def test_extreme_parameters_stay_finite_and_bounded(device, logit):
    model, rest = hanging_sheet(device)
    model = model.to(device)
    generator = torch.Generator().manual_seed(3)
    with torch.no_grad():
        for parameter in model.parameters():
            if logit == "mixed":
                parameter.copy_((torch.randint(0, 2, parameter.shape, generator=generator) * 100.0 - 50.0))
            else:
                parameter.fill_(logit)
    capsules = Capsules(torch.tensor([[0.1, 0.05, -0.1]], device=device),
                        torch.tensor([[0.1, 0.05, -0.3]], device=device), torch.tensor([0.06], device=device))
    state = model.rest_state(rest)
    huge = 1e6 * torch.randn(rest.shape, generator=generator).to(device)
    with torch.no_grad():
        for frame in range(6):
            # frames ten times longer than usual, a jerking attachment, a huge external force
            target = rest[:6] + torch.tensor([0.2 * (-1) ** frame, 0.0, 0.0], device=device)
            state = model.step(state, target, 1 / 3, capsules=capsules, external_acceleration=huge)
            assert torch.isfinite(state.positions).all() and torch.isfinite(state.velocities).all()
            # bounded: no faster than free flight under the capped external acceleration and gravity (what
            # cloth with no stiffness does), however stiff the springs: they cannot blow up
            elapsed, acceleration = (frame + 1) / 3, model.max_external_acceleration + G
            assert state.positions.abs().max() < 1.0 + acceleration * elapsed**2
            assert state.velocities.abs().max() < 10.0 + 2.0 * acceleration * elapsed
    assert model.substeps(1 / 3) == 80
    assert (model.bounded_acceleration(huge).norm(dim=1) <= model.max_external_acceleration * (1 + 1e-6)).all()
    low, high = REST_LENGTH_RANGE
    ratio = model.rest_lengths() / model.rest_length
    assert (ratio >= low - 1e-6).all() and (ratio <= high + 1e-6).all()


def test_the_stiffest_most_damped_lightest_cloth_comes_to_rest(device):
    # The corner of the bounds where the explicit step is closest to instability: stiffness, damping, drag
    # and settling drag at their bounds, the mass at its lower bound. A step outside its stability region
    # would grow exponentially; this one must come to rest.
    model, rest = hanging_sheet(device)
    model = model.to(device)
    with torch.no_grad():
        for parameter in (model.stiffness_logit, model.damping_logit, model.drag_logit):
            parameter.fill_(50.0)
        model.mass_logit.fill_(-50.0)
    state = ClothState(rest + 0.01 * torch.randn(rest.shape, generator=torch.Generator().manual_seed(0)).to(device),
                       torch.zeros_like(rest))
    speeds = []
    with torch.no_grad():
        for _ in range(40):
            state = model.step(state, rest[:6], 1 / 30, extra_drag=1.0)
            speeds.append(state.velocities.norm(dim=1).max().item())
    assert all(math.isfinite(speed) for speed in speeds)
    assert speeds[-1] < 1e-2 * max(speeds)
    with pytest.raises(ValueError, match=r"extra_drag must be in \[0, 1\]"):
        model.step(state, rest[:6], 1 / 30, extra_drag=1.5)


def rollout(model, state, targets, frame_interval, capsules=None, acceleration=None):
    states = []
    for target in targets:
        state = model.step(state, target, frame_interval, capsules=capsules, external_acceleration=acceleration)
        states.append(state)
    return states


def test_cpu_rollout_is_bit_identical():
    results = []
    for _ in range(2):
        model, rest = hanging_sheet("cpu")
        state = ClothState(rest.clone().requires_grad_(), torch.zeros_like(rest))
        targets = [rest[:6] + 0.01 * t for t in range(1, 6)]
        capsules = Capsules(torch.tensor([[0.1, 0.03, -0.05]]), torch.tensor([[0.1, 0.03, -0.25]]),
                            torch.tensor([0.05]))
        final = rollout(model, state, targets, 1 / 30, capsules)[-1]
        loss = (final.positions ** 2).sum() + final.velocities.sum()
        grads = torch.autograd.grad(loss, [state.positions, *model.parameters()])
        results.append((final.positions.detach(), final.velocities.detach(), grads))
    assert torch.equal(results[0][0], results[1][0]) and torch.equal(results[0][1], results[1][1])
    assert all(torch.equal(a, b) for a, b in zip(results[0][2], results[1][2]))


def gradient_problem(device, dtype, seed=12, graph_device=None):
    """A small sheet falling onto a capsule (its middle row in contact at every substep, away from the kinks),
    pinned by one corner that moves, three frames of four substeps; the loss weighs every state by fixed random
    weights; an external acceleration near its bound acts on every node. Returns the loss function of
    (model, x0, v0, acceleration), the model, and (x0, v0, acceleration)."""
    rest = sheet(3, 4, 0.05, horizontal=True) + torch.tensor([-0.075, -0.05, 0.0605])
    # the graph is built where the test runs (a GPU machine's Warp may have no CPU compiler), then moved
    graph = cloth_graph(rest.to(graph_device or device), neighbours=4, bend_per_node=3)
    graph = type(graph)(graph.stretch.cpu(), graph.bend.cpu())
    model = ClothModel(rest, graph, torch.tensor([0]), node_mass=0.02, max_substep=1 / 240)
    generator = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for parameter in model.parameters():
            parameter.add_(0.5 * torch.randn(parameter.shape, generator=generator))
    weights = torch.randn(3, 2, *rest.shape, generator=generator, dtype=torch.float64)
    x0 = rest + 0.01 * torch.randn(rest.shape, generator=generator)
    v0 = 0.1 * torch.randn(rest.shape, generator=generator) - torch.tensor([0.0, 0.0, 0.3])  # onto the capsule
    acceleration = 20.0 * torch.randn(rest.shape, generator=generator)
    capsule = (torch.tensor([[-0.2, 0.0, 0.0]]), torch.tensor([[0.2, 0.0, 0.0]]), torch.tensor([0.06]))
    model = model.to(device=device, dtype=dtype)

    def loss(model, x0, v0, acceleration):
        capsules = Capsules(*(c.to(device=device, dtype=x0.dtype) for c in capsule))
        targets = [x0[:1] + torch.tensor([[0.01, 0.0, 0.005]], device=device, dtype=x0.dtype) * t for t in (1, 2, 3)]
        states = rollout(model, ClothState(x0, v0), targets, 1 / 60, capsules, acceleration)
        w = weights.to(device=device, dtype=x0.dtype)
        return sum((w[t, 0] * s.positions).sum() + 0.01 * (w[t, 1] * s.velocities).sum() for t, s in enumerate(states))

    return loss, model, tuple(value.to(device=device, dtype=dtype) for value in (x0, v0, acceleration))


def gradient_error(analytic, numeric):
    """Largest deviation relative to the largest finite difference of its group."""
    return max((a - n).abs().max().item() / max(n.abs().max().item(), 1e-12) for a, n in zip(analytic, numeric))


def test_rollout_gradients_match_finite_differences(device, monkeypatch):
    # Analytic: the Warp ops in float32 through torch autograd. Numeric: central differences of the same
    # rollout with the ops' float64 torch references (spring_step, cloth_edge_terms, push_out_of_capsules).
    loss, model, state = gradient_problem(device, torch.float32)
    state = [value.clone().requires_grad_() for value in state]
    names = [name for name, _ in model.named_parameters()]
    analytic = torch.autograd.grad(loss(model, *state), [*model.parameters(), *state])
    analytic = [g.double().cpu() for g in analytic]

    contacts = []  # per substep: (nodes pushed, smallest distance of any node to the capsule's surface)

    def recording_collision(x, start, end, radius):
        pushed = reference_collision.push_out_of_capsules(x, start, end, radius)
        if not torch.is_grad_enabled():
            distance = (x[:, 1:] ** 2).sum(dim=1).sqrt()  # the capsule lies along x, past the sheet's ends
            contacts.append((int((pushed != x).any(dim=1).sum()), (distance - radius).abs().min().item()))
        return pushed

    monkeypatch.setattr(ops, "spring_step", reference_springs.spring_step)
    monkeypatch.setattr(ops, "cloth_edge_terms", reference_cloth.cloth_edge_terms)
    monkeypatch.setattr(ops, "push_out_of_capsules", recording_collision)
    model64 = copy.deepcopy(model).to("cpu", torch.float64)
    state64 = [value.detach().cpu().double() for value in state]
    loss, _, _ = gradient_problem("cpu", torch.float64, graph_device=device)  # the same problem, float64, CPU
    inputs = [*model64.parameters(), *state64]
    epsilon = 1e-6
    numeric = []
    with torch.no_grad():
        for value in inputs:
            fd = torch.zeros_like(value)
            for element in range(value.numel()):
                original = value.view(-1)[element].item()
                value.view(-1)[element] = original + epsilon
                plus = loss(model64, *state64).item()
                value.view(-1)[element] = original - epsilon
                minus = loss(model64, *state64).item()
                value.view(-1)[element] = original
                fd.view(-1)[element] = (plus - minus) / (2 * epsilon)
            numeric.append(fd)
    # the rollout touches the capsule at most substeps, and no node comes near the kink of the collision map
    # (the surface) in any rollout of the finite differences, so they differentiate one smooth branch
    substeps = 12
    assert sum(count > 0 for count, _ in contacts[:substeps]) >= 6
    assert min(margin for _, margin in contacts) > 1e-5
    for name, fd in zip(names + ["x0", "v0", "acceleration"], numeric):
        assert fd.abs().max() > 1e-4, name  # every input matters
    # the float64 reference rollout's own autograd agrees tightly (the model's torch code is differentiated right)
    leaves = [value.clone().requires_grad_() for value in state64]
    reference_grads = torch.autograd.grad(loss(model64, *leaves), [*model64.parameters(), *leaves])
    assert gradient_error(reference_grads, numeric) < 1e-5
    # the Warp float32 gradients, within float32 round-off of a 12-substep rollout (measured: 7e-7)
    error = gradient_error(analytic, numeric)
    assert error < 1e-4, (error, [gradient_error([a], [n]) for a, n in zip(analytic, numeric)])
    # the check has teeth: a sign error in one group, or one group 5% off, fails it
    for broken_group in range(len(analytic)):
        flipped = [(-g if k == broken_group else g) for k, g in enumerate(analytic)]
        scaled = [(1.05 * g if k == broken_group else g) for k, g in enumerate(analytic)]
        assert gradient_error(flipped, numeric) > 1e-4 and gradient_error(scaled, numeric) > 1e-4


def test_warp_rollout_matches_the_reference_ops(device, monkeypatch):
    loss, model, state = gradient_problem(device, torch.float32)
    results = []
    for use_reference in (False, True):
        if use_reference:
            monkeypatch.setattr(ops, "spring_step", reference_springs.spring_step)
            monkeypatch.setattr(ops, "cloth_edge_terms", reference_cloth.cloth_edge_terms)
            monkeypatch.setattr(ops, "push_out_of_capsules", reference_collision.push_out_of_capsules)
        leaves = [value.clone().requires_grad_() for value in state]
        value = loss(model, *leaves)
        results.append((value, torch.autograd.grad(value, [*model.parameters(), *leaves])))
    torch.testing.assert_close(results[0][0], results[1][0], rtol=1e-5, atol=1e-5)
    for grad, grad_ref in zip(results[0][1], results[1][1]):
        torch.testing.assert_close(grad, grad_ref, rtol=1e-3, atol=1e-3 * grad_ref.abs().max().item())


def test_bad_options():
    rest = sheet(3, 3, 0.1)
    graph = cloth_graph(rest, neighbours=4, bend_per_node=2)
    with pytest.raises(ValueError, match="max_substep must be > 0"):
        ClothModel(rest, graph, torch.tensor([0]), max_substep=0.0)
    with pytest.raises(ValueError, match="stretch_stiffness is a fraction"):
        ClothModel(rest, graph, torch.tensor([0]), stretch_stiffness=1.0)
    with pytest.raises(ValueError, match=r"attached must hold distinct node ids in \[0, 9\)"):
        ClothModel(rest, graph, torch.tensor([0, 9]))
    with pytest.raises(ValueError, match="attached must hold distinct"):
        ClothModel(rest, graph, torch.tensor([2, 2]))
    with pytest.raises(ValueError, match="node_mass must be positive"):
        ClothModel(rest, graph, torch.tensor([0]), node_mass=0.0)
    with pytest.raises(ValueError, match=r"rest_positions must have shape \[M, 3\]"):
        ClothModel(rest[:, :2], graph, torch.tensor([0]))
    with pytest.raises(ValueError, match=r"strain_limit must be 0 \(off\) or > 1"):
        ClothModel(rest, graph, torch.tensor([0]), strain_limit=0.9)
    with pytest.raises(ValueError, match="strain_iterations must be an integer >= 1"):
        ClothModel(rest, graph, torch.tensor([0]), strain_limit=1.1, strain_iterations=0)
    with pytest.raises(ValueError, match="bend_per_node must be >= 0"):
        cloth_graph(rest, bend_per_node=-1)
