"""Tests of the triangle-mesh cloth: :func:`warpavatar.ops.sheet_forces` and :func:`warpavatar.ops.sheet_rollout`
against their plain-torch references (values, and gradients with random cotangents, on every device), the Warp
forces against central differences of the float64 energies (near rest and past the membrane's strain cap), and
:class:`warpavatar.sim.SheetCloth`: its hinges, its stability bounds (a skirt hanging from its ring at the largest
stiffness stays finite and near its length, and so does one whose pins jump through a capsule; eight times the
membrane bound diverges), capsule collision, frames stepped one by one against one rollout, and bad input."""

import math

import pytest
import torch

from conftest import assert_matches_central_differences, load_tool
from warpavatar import ops
from warpavatar._src.sheet_cloth import dihedral_angles, sheet_mesh
from warpavatar._torch_impl import sheet_cloth as reference
from warpavatar.sim import Capsules, SheetCloth, SheetState, sheet_hinges

make_skirt = load_tool("bench_sheet_cloth").make_skirt
NEAR_ONE = 1.0 - 1e-4  # a parameter at its bound, as far as a finite logit goes


def random_sheet(seed, device, *, rows=6, columns=10, pinned=3):
    """A perturbed skirt, its SheetMesh (the first ``pinned`` ring vertices pinned), a deformed moving state and
    random per-element parameters of realistic size."""
    generator = torch.Generator().manual_seed(seed)
    rest, faces, _ = make_skirt(rows, columns, radius=0.15, length=0.3, noise=0.15, seed=seed)
    hinges, hinge_triangles = sheet_hinges(faces, rest.shape[0])
    mass = 0.002 + 0.002 * torch.rand(rest.shape[0], generator=generator)
    mesh = sheet_mesh(rest.to(device), faces.to(device), hinges.to(device), hinge_triangles.to(device),
                      mass.to(device), torch.arange(pinned, device=device))
    triangle_count, hinge_count = faces.shape[0], hinges.shape[0]

    def uniform(low, high, count):
        return (low + (high - low) * torch.rand(count, generator=generator)).to(device)

    state = {
        "positions": (rest + 0.01 * torch.randn(rest.shape, generator=generator)).to(device),
        "velocities": (0.3 * torch.randn(rest.shape, generator=generator)).to(device),
    }
    parameters = {
        "stretch_stiffness": uniform(2.0, 8.0, triangle_count),
        "shear_stiffness": uniform(1.0, 4.0, triangle_count),
        "bend_stiffness": uniform(1e-4, 1e-3, hinge_count),
        "drag_coefficient": uniform(0.5, 2.0, triangle_count),
    }
    return mesh, state, parameters


FORCE_INPUTS = ("positions", "velocities", "stretch_stiffness", "shear_stiffness", "bend_stiffness",
                "drag_coefficient")


def call_forces(op, mesh, inputs):
    return op(inputs["positions"], inputs["velocities"], mesh, inputs["stretch_stiffness"], inputs["shear_stiffness"],
              inputs["bend_stiffness"], inputs["drag_coefficient"])


def leaves(inputs, names):
    return {name: inputs[name].detach().clone().requires_grad_(True) for name in names}


@pytest.mark.parametrize("seed", [0, 1])
def test_forces_and_their_gradients_match_the_reference(device, seed):
    mesh, state, parameters = random_sheet(seed, device)
    inputs = leaves({**state, **parameters}, FORCE_INPUTS)
    ours = call_forces(ops.sheet_forces, mesh, inputs)
    theirs = call_forces(reference.sheet_forces, mesh, inputs)
    scale = theirs.abs().max().item()
    assert scale > 1e-2
    torch.testing.assert_close(ours, theirs, rtol=1e-4, atol=1e-5 * scale)
    cotangent = torch.randn_like(ours)
    names = list(inputs)
    grads_ours = torch.autograd.grad(ours, [inputs[n] for n in names], cotangent)
    grads_theirs = torch.autograd.grad(theirs, [inputs[n] for n in names], cotangent)
    for name, grad_ours, grad_theirs in zip(names, grads_ours, grads_theirs):
        grad_scale = grad_theirs.abs().max().item()
        assert grad_scale > 0, name
        torch.testing.assert_close(grad_ours, grad_theirs, rtol=1e-3, atol=1e-4 * grad_scale,
                                   msg=lambda m, n=name: f"{n}: {m}")


@pytest.mark.parametrize("stretch", [1.0, 1.8])
def test_forces_are_minus_the_energy_gradient_by_central_differences(stretch):
    # The kernels' hand-written force formulas against central differences of the float64 energies, term by term,
    # near rest and stretched 1.8 times along x (most triangles past the membrane's strain cap).
    mesh, state, parameters = random_sheet(2, "cpu", rows=4, columns=6)
    state["positions"] = state["positions"] * torch.tensor([stretch, 1.0, 1.0])
    x = state["positions"].double()
    zero_t, zero_h = torch.zeros_like(parameters["stretch_stiffness"]), torch.zeros_like(parameters["bend_stiffness"])
    still = torch.zeros_like(state["positions"])
    terms = {
        "stretch": ((parameters["stretch_stiffness"], zero_t, zero_h),
                    lambda p: reference.membrane_energy(p["x"], mesh, parameters["stretch_stiffness"], zero_t)),
        "shear": ((zero_t, parameters["shear_stiffness"], zero_h),
                  lambda p: reference.membrane_energy(p["x"], mesh, zero_t, parameters["shear_stiffness"])),
        "bending": ((zero_t, zero_t, parameters["bend_stiffness"]),
                    lambda p: reference.bending_energy(p["x"], mesh, parameters["bend_stiffness"])),
    }
    for name, ((stretch, shear, bend), energy) in terms.items():
        force = ops.sheet_forces(state["positions"], still, mesh, stretch, shear, bend, zero_t)
        assert_matches_central_differences(lambda p: float(energy(p)), {"x": x}, {"x": -force}, epsilon=1e-6,
                                           rtol=2e-3, relative_atol=1e-4, min_scale=1e-4)


def test_bending_angle_and_hinges_of_a_folded_square():
    # two triangles (0, 1, 2) and (1, 0, 3) sharing the edge 0-1 along x; vertex 3 lifted folds the hinge
    positions = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.5, 1.0, 0.0], [0.5, -1.0, 0.0]])
    faces = torch.tensor([[0, 1, 2], [1, 0, 3]])
    hinges, hinge_triangles = sheet_hinges(faces, 4)
    assert hinges.shape == (1, 4) and sorted(hinges[0, :2].tolist()) == [0, 1]
    assert sorted(hinges[0, 2:].tolist()) == [2, 3] and sorted(hinge_triangles[0].tolist()) == [0, 1]
    assert dihedral_angles(positions, hinges).abs().item() < 1e-7  # flat
    for lift in (0.5, -0.5):
        folded = positions.clone()
        folded[3, 2] = lift
        angle = dihedral_angles(folded, hinges).item()
        assert abs(abs(angle) - math.atan2(0.5, 1.0)) < 1e-6
    # the flat rest hinge pushes a folded one back towards flat, and the forces sum to zero
    mesh = sheet_mesh(positions, faces, hinges, hinge_triangles, torch.ones(4), torch.zeros(0, dtype=torch.long))
    folded = positions.clone()
    folded[3, 2] = 0.5
    force = ops.sheet_forces(folded, torch.zeros_like(folded), mesh, torch.zeros(2), torch.zeros(2), torch.ones(1),
                             torch.zeros(2))
    assert force[3, 2] < 0 and force.sum(0).abs().max() < 1e-6


def rollout_inputs(seed, device, *, frames=3, substeps=4, capsules=True):
    mesh, state, parameters = random_sheet(seed, device)
    generator = torch.Generator().manual_seed(100 + seed)
    substep_count = frames * substeps
    pinned_rest = state["positions"][: mesh.pinned_count].cpu()
    pin_targets = pinned_rest[None] + 0.01 * torch.randn(substep_count, mesh.pinned_count, 3, generator=generator)
    inputs = {**state, **parameters,
              "damping": (0.5 + torch.rand(mesh.vertex_count, generator=generator)).to(device),
              "pin_targets": pin_targets.to(device),
              "pin_velocities": 0.2 * torch.randn(substep_count, mesh.pinned_count, 3, generator=generator).to(device)}
    if capsules:
        # a capsule along the skirt's axis, just inside it (most vertices start within a few mm of its surface, some
        # inside), and a small one across the hem
        start = torch.tensor([[0.0, 0.0, -0.35], [0.05, -0.2, -0.25]]) + 0.002 * torch.randn(substep_count, 2, 3,
                                                                                             generator=generator)
        end = torch.tensor([[0.0, 0.0, 0.05], [0.05, 0.2, -0.25]]).expand(substep_count, -1, -1)
        radius = torch.tensor([0.146, 0.04]).expand(substep_count, -1)
        inputs.update(capsule_start=start.to(device), capsule_end=end.contiguous().to(device),
                      capsule_radius=radius.contiguous().to(device))
    return mesh, inputs, substeps


ROLLOUT_INPUTS = (*FORCE_INPUTS, "damping", "pin_targets", "pin_velocities")
CAPSULE_INPUTS = ("capsule_start", "capsule_end", "capsule_radius")


def call_rollout(op, mesh, inputs, substeps, h=1.0 / 600.0):
    capsules = (tuple(inputs[name] for name in CAPSULE_INPUTS) if "capsule_start" in inputs else None)
    return op(*(inputs[name] for name in ("positions", "velocities")), mesh,
              *(inputs[name] for name in ROLLOUT_INPUTS[2:]), substep=h, substeps_per_frame=substeps,
              gravity=(0.0, 0.0, -9.81), capsules=capsules)


@pytest.mark.parametrize("capsules", [True, False])
def test_rollout_and_its_gradients_match_the_reference(device, capsules):
    mesh, inputs, substeps = rollout_inputs(3, device, capsules=capsules)
    names = ROLLOUT_INPUTS + (CAPSULE_INPUTS if capsules else ())
    inputs = leaves(inputs, names)
    ours = call_rollout(ops.sheet_rollout, mesh, inputs, substeps)
    theirs = call_rollout(reference.sheet_rollout, mesh, inputs, substeps)
    for value_ours, value_theirs in zip(ours, theirs):
        assert value_ours.shape == (3, mesh.vertex_count, 3)
        torch.testing.assert_close(value_ours, value_theirs, rtol=1e-4, atol=1e-4 * value_theirs.abs().max().item())
    if capsules:  # the scene tests the collision: some vertex was pushed
        pushed = call_rollout(reference.sheet_rollout, mesh, {n: v for n, v in inputs.items()
                                                              if n not in CAPSULE_INPUTS}, substeps)[0]
        assert (pushed - theirs[0]).abs().max() > 1e-3
    cotangents = [torch.randn_like(value) for value in ours]
    grads_ours = torch.autograd.grad(ours, [inputs[n] for n in names], cotangents)
    grads_theirs = torch.autograd.grad(theirs, [inputs[n] for n in names], cotangents)
    for name, grad_ours, grad_theirs in zip(names, grads_ours, grads_theirs):
        grad_scale = grad_theirs.abs().max().item()
        assert grad_scale > 0, name
        torch.testing.assert_close(grad_ours, grad_theirs, rtol=2e-3, atol=2e-4 * grad_scale,
                                   msg=lambda m, n=name: f"{n}: {m}")
    # without gradients the same rollout (the ping-pong path) gives the same frames (bit for bit on the CPU; on a
    # GPU the atomic sums may add in another order)
    with torch.no_grad():
        plain = call_rollout(ops.sheet_rollout, mesh, inputs, substeps)
    exact = torch.device(device).type == "cpu"
    for value_plain, value_ours in zip(plain, ours):
        torch.testing.assert_close(value_plain, value_ours, rtol=0 if exact else 1e-5,
                                   atol=0 if exact else 1e-5 * value_ours.abs().max().item())


def hanging_skirt(device, *, fraction=NEAR_ONE, **options):
    rest, faces, ring = make_skirt(9, 24, radius=0.2, length=0.4, noise=0.1)
    cloth = SheetCloth(rest.to(device), faces.to(device), ring.to(device), max_substep=1.0 / 600.0,
                       stretch_stiffness=fraction, shear_stiffness=fraction, bend_stiffness=fraction,
                       damping=1e-3, drag=1e-3, **options)
    return cloth, rest.to(device), ring.to(device)


def test_a_skirt_hanging_at_the_largest_stiffness_stays_finite_and_near_its_length(device):
    cloth, rest, ring = hanging_skirt(device)
    assert cloth.stretch_stiffness().item() == pytest.approx(cloth.max_membrane_stiffness, rel=1e-3)
    ring_rest = rest[ring]
    length = (rest[:, None] - ring_rest[None]).norm(dim=-1).amin(dim=1).max().item()
    substeps = 200
    with torch.no_grad():  # 200 substeps of 1/600 s, one frame each, the ring held still
        positions, velocities = cloth.rollout(cloth.rest_state(), ring_rest[None].expand(substeps, -1, -1),
                                              1.0 / 600.0)
    assert bool(torch.isfinite(positions).all()) and bool(torch.isfinite(velocities).all())
    reach = (positions[:, :, None] - ring_rest[None, None]).norm(dim=-1).amin(dim=2).amax(dim=1)
    assert reach.max().item() < 1.25 * length, (reach.max().item(), length)  # it stretches a few per cent
    assert reach.max().item() > 1.01 * length  # and does hang: gravity pulls it
    assert velocities[-1].norm(dim=1).max().item() < 2.0


def test_violent_pins_and_deep_collisions_stay_finite(device):
    # the pins jump 10 cm a frame in random directions and a fat capsule starts deep inside the skirt: the cloth is
    # stretched far past its strain cap and crumpled, and stays finite (the capped membrane's stiffness is bounded)
    cloth, rest, ring = hanging_skirt(device)
    frames = 30
    generator = torch.Generator().manual_seed(0)
    pins = rest[ring][None] + (0.1 * torch.randn(frames, 1, 3, generator=generator)).to(device)
    start = torch.tensor([[0.0, 0.0, -0.5]], device=device).expand(frames, -1, -1)
    capsules = Capsules(start, start + torch.tensor([0.1, 0.0, 0.6], device=device),
                        torch.full((frames, 1), 0.23, device=device))
    with torch.no_grad():
        positions, velocities = cloth.rollout(cloth.rest_state(), pins, 1.0 / 30.0, capsules=capsules)
    assert bool(torch.isfinite(positions).all()) and bool(torch.isfinite(velocities).all())
    assert positions.abs().max().item() < 5.0


def test_eight_times_the_membrane_bound_diverges():
    # the bound is within a small factor of the real limit (an explicit step is stable up to 4 / 0.8 times it
    # at rest): far above it the same skirt blows up
    cloth, rest, ring = hanging_skirt("cpu")
    mesh = cloth.mesh
    stiff = torch.full((mesh.triangle_count,), 8.0 * cloth.max_membrane_stiffness)
    substeps = 600
    with torch.no_grad():
        positions, _ = ops.sheet_rollout(
            rest, torch.zeros_like(rest), mesh, stiff, stiff, torch.zeros(mesh.hinge_count), torch.zeros_like(stiff),
            torch.zeros(mesh.vertex_count), rest[ring][None].expand(substeps, -1, -1).contiguous(),
            torch.zeros(substeps, ring.shape[0], 3), substep=1.0 / 600.0, substeps_per_frame=substeps)
    assert not bool(torch.isfinite(positions).all()) or positions.abs().max() > 10.0


def test_capsules_keep_the_skirt_outside(device):
    # a leg capsule swings sideways through the hanging skirt over 10 frames: no free vertex is left inside
    cloth, rest, ring = hanging_skirt(device, fraction=0.5)
    frames = 10
    swing = torch.linspace(-0.3, 0.3, frames + 1, device=device)
    start = torch.stack([swing, torch.zeros_like(swing), torch.full_like(swing, -0.45)], dim=1)[:, None]
    end = start + torch.tensor([0.0, 0.0, 0.4], device=device)
    radius = torch.full((frames + 1, 1), 0.06, device=device)
    capsules = Capsules(start[1:], end[1:], radius[1:])
    with torch.no_grad():
        positions, _ = cloth.rollout(cloth.rest_state(), rest[ring][None].expand(frames, -1, -1), 1.0 / 30.0,
                                     capsules=capsules, initial_capsules=Capsules(start[0], end[0], radius[0]))
    free = torch.ones(cloth.vertex_count, dtype=torch.bool, device=device)
    free[ring] = False
    for frame in range(frames):
        a, b = start[frame + 1, 0], end[frame + 1, 0]
        x = positions[frame][free]
        t = ((x - a) @ (b - a) / (b - a).dot(b - a)).clamp(0, 1)
        distance = (x - a - t[:, None] * (b - a)).norm(dim=1)
        assert distance.min().item() >= 0.06 - 1e-5, (frame, distance.min().item())
    # and the leg did reach the cloth: some vertex was moved by more than the hanging alone moves it
    with torch.no_grad():
        alone, _ = cloth.rollout(cloth.rest_state(), rest[ring][None].expand(frames, -1, -1), 1.0 / 30.0)
    assert (positions - alone).norm(dim=-1).max() > 0.05


def test_steps_one_frame_at_a_time_equal_one_rollout_and_gradients_reach_every_parameter():
    cloth, rest, ring = hanging_skirt("cpu", fraction=0.5)
    frames = 3
    pins = rest[ring][None] + torch.tensor([0.02, 0.0, 0.01]) * torch.arange(1, frames + 1)[:, None, None]
    positions, velocities = cloth.rollout(cloth.rest_state(), pins, 1.0 / 30.0)
    state = cloth.rest_state()
    for frame in range(frames):
        state = cloth.step(state, pins[frame], 1.0 / 30.0)
        torch.testing.assert_close(state.positions, positions[frame], rtol=0, atol=1e-6)
    assert torch.equal(positions[:, ring], pins)  # pinned vertices land on their targets
    assert cloth.substeps(1.0 / 30.0) == 20
    loss = (positions[-1] ** 2).sum() + velocities.sum()
    loss.backward()
    for name, parameter in cloth.named_parameters():
        assert parameter.grad is not None and torch.isfinite(parameter.grad) and parameter.grad != 0, name


def test_bad_input_is_refused_in_one_line():
    rest, faces, ring = make_skirt(3, 6)
    with pytest.raises(ValueError, match="belong to no triangle"):
        SheetCloth(torch.cat([rest, torch.zeros(1, 3)]), faces, ring)
    with pytest.raises(ValueError, match="stretch_stiffness is a fraction of its bound"):
        SheetCloth(rest, faces, ring, stretch_stiffness=1.0)
    with pytest.raises(ValueError, match="distinct vertex ids"):
        SheetCloth(rest, faces, torch.tensor([0, 0]))
    cloth = SheetCloth(rest, faces, ring)
    with pytest.raises(ValueError, match="substeps must be an integer >= 20"):
        cloth.step(cloth.rest_state(), rest[ring], 1.0 / 30.0, substeps=10)
    with pytest.raises(ValueError, match=r"pinned_positions must have shape \[F, 6, 3\]"):
        cloth.rollout(cloth.rest_state(), rest[ring], 1.0 / 30.0)
    state = SheetState(rest.double(), torch.zeros_like(rest))
    with pytest.raises(TypeError, match="positions must be float32"):
        cloth.step(state, rest[ring].double(), 1.0 / 30.0)
