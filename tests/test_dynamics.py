"""SMAD's learned secondary dynamics: drive features, the spring-damper step, rollouts, gradients, lookups, files."""

import math

import pytest
import torch

from warpavatar import ops
from warpavatar._torch_impl.springs import spring_step as reference_spring_step
from warpavatar.extensions.dynamics import DynamicsState, SecondaryDynamics
from warpavatar.model import frame_intervals

PARENTS = [-1, 0, 1, 0]


def _rotation(axis, angle):
    axis = torch.as_tensor(axis, dtype=torch.float64)
    axis = axis / axis.norm()
    cross = torch.tensor([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]],
                         dtype=torch.float64)
    return torch.eye(3, dtype=torch.float64) + math.sin(angle) * cross + (1 - math.cos(angle)) * cross @ cross


def _motion(frame_count, generator, *, joint_count=len(PARENTS), speed=1.0):
    """A smooth random motion: every bone turns about its own axis and the whole body drifts and sways."""
    axes = torch.randn(joint_count, 3, generator=generator, dtype=torch.float64)
    rates = torch.rand(joint_count, generator=generator, dtype=torch.float64) * 0.4 * speed
    sway = torch.rand(3, generator=generator, dtype=torch.float64) * 0.05 * speed
    poses = torch.eye(4, dtype=torch.float64).repeat(frame_count, joint_count, 1, 1)
    for t in range(frame_count):
        for j in range(joint_count):
            poses[t, j, :3, :3] = _rotation(axes[j], rates[j] * t)
            poses[t, j, :3, 3] = sway * math.sin(0.3 * t) + torch.tensor([0.01 * speed * t, 0.0, 0.0],
                                                                          dtype=torch.float64)
    return poses.float()


def _module(device, *, node_count=48, seed=0, substeps=2, hidden=16, **options):
    generator = torch.Generator().manual_seed(seed)
    nodes = torch.rand(node_count, 3, generator=generator)
    weights = torch.softmax(3.0 * torch.randn(node_count, len(PARENTS), generator=generator), dim=1)
    module = SecondaryDynamics(nodes.to(device), weights.to(device), PARENTS, voxel_size=0.15,
                               frame_interval=1.0 / 30.0, neighbors=6, hidden=hidden, embedding=8,
                               velocity_history=3, pose_window=2, substeps=substeps, **options)
    return module, generator


def _silence_network(module):
    with torch.no_grad():
        module.force_head.weight.zero_()
        module.force_head.bias.zero_()


def _randomize(module, generator, scale=0.5):
    """Non-trivial learnable values (never the initial constants) in every parameter."""
    with torch.no_grad():
        for parameter in module.parameters():
            parameter.add_(scale * torch.randn(parameter.shape, generator=generator).to(parameter.device))


def test_frame_intervals():
    intervals = frame_intervals([0, 1, 3, 6], 30.0)
    assert torch.allclose(intervals, torch.tensor([2.0, 1.0, 2.0, 3.0]) / 30.0)
    assert torch.allclose(frame_intervals([7], 25.0), torch.tensor([1.0 / 25.0]))
    with pytest.raises(ValueError, match="strictly increasing"):
        frame_intervals([0, 2, 2], 30.0)
    with pytest.raises(ValueError, match="fps"):
        frame_intervals([0, 1], 0.0)


def test_drive_matches_a_direct_computation(device):
    module, generator = _module(device)
    poses = _motion(6, generator).to(device)
    intervals = frame_intervals([0, 1, 2, 4, 5, 7], 30.0).to(device)
    drive = module.drive(poses, intervals)
    weights = module.node_weights.double().cpu()
    nodes = module.nodes.double().cpu()
    bones = poses.double().cpu()
    dt = intervals.double().cpu()
    speed = module.speed_unit
    history = module.hyper["velocity_history"]
    for t in range(6):
        blended = torch.einsum("mj,jab->mab", weights, bones[t])
        rotation = blended[:, :3, :3]

        def position(s):
            b = torch.einsum("mj,jab->mab", weights, bones[s])
            return torch.einsum("mab,mb->ma", b[:, :3, :3], nodes) + b[:, :3, 3]

        def velocity(s):
            return (position(s) - position(s - 1)) / dt[s] if s >= 1 else torch.zeros_like(nodes)

        for lag in range(history):
            expected = torch.einsum("mba,mb->ma", rotation, velocity(t - lag)) / speed if t - lag >= 0 \
                else torch.zeros_like(nodes)
            got = drive["velocities"][t, :, 3 * lag: 3 * lag + 3].double().cpu()
            assert torch.allclose(got, expected, rtol=1e-4, atol=1e-4), (t, lag)
        acceleration = (velocity(t) - velocity(t - 1)) / dt[t] if t >= 2 else torch.zeros_like(nodes)
        expected = torch.einsum("mba,mb->ma", rotation, acceleration)
        assert torch.allclose(drive["acceleration"][t].double().cpu(), expected, rtol=1e-4, atol=1e-3), t
    # pose features: rotation of each bone relative to the root, for this frame then the one before
    relative = torch.linalg.solve(bones[3, 0], bones[3])[:, :3, :2].reshape(-1)
    previous = torch.linalg.solve(bones[2, 0], bones[2])[:, :3, :2].reshape(-1)
    assert torch.allclose(drive["pose_features"][3].double().cpu(), torch.cat([relative, previous]), atol=1e-5)


def test_step_is_the_spring_damper_euler_step_when_the_network_is_silent(device):
    module, generator = _module(device, substeps=1)
    _silence_network(module)
    _randomize(module, generator, scale=0.3)
    _silence_network(module)
    poses = _motion(4, generator).to(device)
    intervals = frame_intervals(torch.arange(4), 30.0).to(device)
    drive = module.drive(poses, intervals)
    state = DynamicsState(0.02 * torch.randn(module.node_count, 3, generator=generator).to(device),
                          0.1 * torch.randn(module.node_count, 3, generator=generator).to(device))
    with torch.no_grad():
        result = module.step(state, drive, 3, float(intervals[3]))
    d, u = state.displacement.double(), state.velocity.double()
    k, anchor, gamma = module.stiffness.double(), module.anchor.double(), module.damping_coefficient.double()
    receivers, senders = module.edges[:, 0].long(), module.edges[:, 1].long()
    spring = torch.zeros_like(d).index_add_(0, receivers, k[:, None] * (d[receivers] - d[senders]))
    acceleration = -drive["acceleration"][3].double() - anchor[:, None] * d - gamma[:, None] * u - spring
    dt = float(intervals[3])
    u_next = u + dt * acceleration
    d_next = d + dt * u_next
    assert torch.allclose(result.velocity.double(), u_next, rtol=1e-4, atol=1e-5)
    assert torch.allclose(result.displacement.double(), d_next, rtol=1e-4, atol=1e-6)


def test_still_body_keeps_a_silent_graph_at_rest(device):
    module, generator = _module(device)
    _silence_network(module)
    poses = _motion(1, generator).to(device).repeat(12, 1, 1, 1)
    displacement, velocity = module.rollout(poses, frame_intervals(torch.arange(12), 30.0).to(device))
    assert displacement.shape == (12, module.node_count, 3)
    assert float(displacement.abs().max()) == 0.0 and float(velocity.abs().max()) == 0.0


def test_loose_nodes_lag_behind_an_accelerating_body(device):
    module, generator = _module(device)
    _silence_network(module)
    frame_count = 8
    poses = torch.eye(4).repeat(frame_count, len(PARENTS), 1, 1)
    for t in range(frame_count):
        poses[t, :, 0, 3] = 0.004 * t * t  # constant acceleration along +x, no rotation
    poses = poses.to(device)
    intervals = frame_intervals(torch.arange(frame_count), 30.0).to(device)
    stiff, _ = module.rollout(poses, intervals)
    with torch.no_grad():
        module.anchor_raw.fill_(-3.0)  # softer anchor springs
    loose, _ = module.rollout(poses, intervals)
    assert bool((stiff[-1, :, 0] < 0).all()), "nodes should be left behind along -x"
    assert float(loose[-1, :, 0].mean()) < float(stiff[-1, :, 0].mean()) < 0
    assert float(stiff[-1, :, 1:].abs().max()) < 1e-5  # nothing pushes them sideways


def test_step_matches_the_torch_reference_values_and_gradients(device, monkeypatch):
    module, generator = _module(device)
    _randomize(module, generator, scale=0.2)
    poses = _motion(5, generator).to(device)
    intervals = frame_intervals(torch.arange(5), 30.0).to(device)
    drive = module.drive(poses, intervals)
    weights = torch.randn(module.node_count, 3, generator=generator).to(device)

    def run():
        module.zero_grad(set_to_none=True)
        state = module.rest_state()
        for frame in range(1, 5):
            state = module.step(state, drive, frame, float(intervals[frame]))
        loss = (state.displacement * weights).sum() + (state.velocity * weights).sum() * 0.1
        loss.backward()
        return state, {name: p.grad.clone() for name, p in module.named_parameters()}

    state, grads = run()
    monkeypatch.setattr(ops, "spring_step", reference_spring_step)
    reference_state, reference_grads = run()
    assert float(state.displacement.detach().abs().max()) > 1e-5  # the motion moved the graph
    assert torch.allclose(state.displacement, reference_state.displacement, rtol=1e-4, atol=1e-7)
    assert torch.allclose(state.velocity, reference_state.velocity, rtol=1e-4, atol=1e-6)
    for name, grad in grads.items():
        reference = reference_grads[name]
        scale = float(reference.abs().max())
        assert scale > 0, f"no gradient reaches {name}"
        assert float((grad - reference).abs().max()) <= 1e-3 * scale + 1e-8, name


def test_gradients_match_finite_differences(device):
    module, generator = _module(device, node_count=24)
    _randomize(module, generator, scale=0.2)
    poses = _motion(5, generator, speed=3.0).to(device)
    intervals = frame_intervals(torch.arange(5), 30.0).to(device)
    drive = module.drive(poses, intervals)
    weights = torch.randn(module.node_count, 3, generator=generator).to(device)

    def loss_value():
        state = module.rest_state()
        for frame in range(1, 5):
            state = module.step(state, drive, frame, float(intervals[frame]))
        return (state.displacement * weights).sum() * 100.0

    module.zero_grad(set_to_none=True)
    loss_value().backward()
    probes = [(module.anchor_raw, 3), (module.damping_raw, 5), (module.stiffness_raw, 7),
              (module.force_head.bias, 1), (module.force_head.weight, 4)]
    for parameter, flat_index in probes:
        analytic = float(parameter.grad.reshape(-1)[flat_index])
        step = 1e-2
        with torch.no_grad():
            flat = parameter.view(-1)
            original = float(flat[flat_index])
            flat[flat_index] = original + step
            plus = float(loss_value())
            flat[flat_index] = original - step
            minus = float(loss_value())
            flat[flat_index] = original
        numeric = (plus - minus) / (2 * step)
        assert abs(analytic - numeric) <= 0.03 * max(abs(numeric), abs(analytic)) + 1e-4, \
            (parameter.shape, flat_index, analytic, numeric)


def test_rollout_stays_bounded_for_extreme_parameters(device):
    module, generator = _module(device)
    with torch.no_grad():
        module.stiffness_raw.fill_(30.0)  # every bound at its top (or the anchor at its bottom)
        module.damping_raw.fill_(30.0)
        module.anchor_raw.fill_(-30.0)
        module.force_head.bias.fill_(0.0)
    poses = _motion(150, generator, speed=4.0).to(device)
    displacement, velocity = module.rollout(poses, frame_intervals(torch.arange(150), 30.0).to(device))
    assert bool(torch.isfinite(displacement).all()) and bool(torch.isfinite(velocity).all())
    assert float(displacement.abs().max()) < 50.0


def test_rollout_stays_bounded_for_sparse_frames_and_a_runaway_network(device):
    module, generator = _module(device)
    with torch.no_grad():
        module.stiffness_raw.fill_(30.0)
        module.damping_raw.fill_(-30.0)  # no damping at all
        module.anchor_raw.fill_(30.0)
        module.force_head.bias.fill_(1e6)  # the network pushes as hard as it may
        module.force_head.weight.fill_(1e3)  # ... and feeds back on the state
    poses = _motion(40, generator, speed=4.0).to(device)
    every_fifth = frame_intervals(torch.arange(40) * 5, 30.0).to(device)  # frames 5x farther apart than trained
    displacement, velocity = module.rollout(poses, every_fifth)
    assert bool(torch.isfinite(displacement).all()) and bool(torch.isfinite(velocity).all())
    voxel = module.hyper["voxel_size"]
    # bounded force over the stiffest anchor: |d| stays within a few (force limit / anchor) lengths
    assert float(displacement.abs().max()) < 20.0 * voxel


def _with_training_rollout(device):
    """A randomized module whose table holds the rollout of a 6-frame training motion."""
    module, generator = _module(device)
    _randomize(module, generator, scale=0.2)
    training = _motion(6, generator).to(device)
    intervals = frame_intervals(torch.arange(6), 30.0).to(device)
    displacement, _ = module.rollout(training, intervals)
    module.set_training_rollout(training, displacement)
    return module, generator, training, intervals, displacement


def test_lookup_prefers_training_frames_then_the_prepared_motion(device):
    module, generator, training, _, displacement = _with_training_rollout(device)
    assert torch.equal(module.node_displacement(training[4]), displacement[4])
    other = _motion(5, generator, speed=2.0).to(device)
    unknown = other[3]
    assert float(module.node_displacement(unknown).abs().max()) == 0.0
    module.prepare_sequence(other, frame_intervals(torch.arange(5), 30.0).to(device))
    rolled, _ = module.rollout(other, frame_intervals(torch.arange(5), 30.0).to(device))
    assert float(rolled[3].abs().max()) > 0
    assert torch.allclose(module.node_displacement(unknown), rolled[3], atol=1e-6)  # CUDA atomics: last bits
    assert torch.equal(module.node_displacement(training[2]), displacement[2])


def test_file_round_trip(device):
    module, generator, poses, intervals, displacement = _with_training_rollout(device)
    means = torch.rand(30, 3, generator=generator).to(device)
    module.bind(means)
    loaded = SecondaryDynamics.from_file_state(module.state_for_file(), device=device)
    again, _ = loaded.rollout(poses, intervals)
    assert torch.allclose(again, displacement, atol=1e-6)
    assert torch.equal(loaded.node_displacement(poses[5]), module.node_displacement(poses[5]))
    values = 0.1 * torch.randn(module.node_count, 3, generator=generator).to(device)
    assert torch.allclose(loaded.gaussian_displacement(means, values), module.gaussian_displacement(means, values))


def test_bad_inputs_are_clear_errors():
    nodes = torch.rand(10, 3)
    weights = torch.softmax(torch.randn(10, 4), dim=1)
    with pytest.raises(ValueError, match="node_weights must have shape"):
        SecondaryDynamics(nodes, weights[:, :3], PARENTS, voxel_size=0.2, frame_interval=0.03)
    with pytest.raises(ValueError, match="no root"):
        SecondaryDynamics(nodes, weights, [1, 0, 1, 0], voxel_size=0.2, frame_interval=0.03)
    with pytest.raises(ValueError, match="hidden must be at least 1"):
        SecondaryDynamics(nodes, weights, PARENTS, voxel_size=0.2, frame_interval=0.03, hidden=0)
    with pytest.raises(ValueError, match="frame_interval"):
        SecondaryDynamics(nodes, weights, PARENTS, voxel_size=0.2, frame_interval=float("nan"))
    module = SecondaryDynamics(nodes, weights, PARENTS, voxel_size=0.2, frame_interval=0.03, neighbors=4)
    with pytest.raises(ValueError, match=r"bone_transforms must have shape \[T, 4, 4, 4\]"):
        module.drive(torch.eye(4).repeat(3, 3, 1, 1), torch.ones(3))
    with pytest.raises(ValueError, match="intervals must have shape"):
        module.drive(torch.eye(4).repeat(3, 4, 1, 1), torch.ones(2))
