"""Tests of :func:`warpavatar.ops.corrected_poses` and :func:`warpavatar.ops.pose_priors` (the pose refinement's Warp
kernels) against their plain-torch references and central differences, on every device.

Skeletons are forests whose joints are not numbered parents first (a parent after its child), poses are random
rigid transforms, corrections random (some below the small-angle threshold of the exponential map, some exactly
zero), and the frames of the priors lie unevenly apart in time.
"""

import pytest
import torch

from conftest import assert_matches_central_differences
from warpavatar import ops
from warpavatar._torch_impl import poses as reference
from warpavatar.geometry import quat_to_matrix
from warpavatar.model.kinematics import ancestor_jumps, corrected_transforms

# two trees: joint 0 (parent 3, numbered before it), and joints 7.. rooted at 6
PARENTS = [3, 0, 1, -1, 3, 4, -1, 6, 7, 6]


def random_poses(frames, seed, *, parents=PARENTS, dtype=torch.float64):
    generator = torch.Generator().manual_seed(seed)
    joints = len(parents)
    quats = torch.randn(frames * joints, 4, generator=generator, dtype=torch.float64)
    poses = torch.zeros(frames, joints, 4, 4, dtype=torch.float64)
    poses[..., :3, :3] = quat_to_matrix(quats / quats.norm(dim=-1, keepdim=True)).reshape(frames, joints, 3, 3)
    poses[..., :3, 3] = torch.randn(frames, joints, 3, generator=generator, dtype=torch.float64)
    poses[..., 3, 3] = 1.0
    scene = {
        "bone_transforms": poses,
        "heads": torch.randn(joints, 3, generator=generator, dtype=torch.float64),
        "rotation": 0.4 * torch.randn(frames, joints, 3, generator=generator, dtype=torch.float64),
        "translation": 0.3 * torch.randn(frames, 3, generator=generator, dtype=torch.float64),
    }
    scene["rotation"][0, 0] = 1e-5  # Rodrigues' Taylor branch
    scene["rotation"][-1, -1] = 0.0
    return {name: value.to(dtype) for name, value in scene.items()}


def prior_inputs(frames, seed, *, dtype=torch.float64):
    scene = random_poses(frames, seed, dtype=torch.float64)
    generator = torch.Generator().manual_seed(seed + 100)
    joints = len(PARENTS)
    poses = reference.corrected_poses(scene["bone_transforms"], scene["heads"], PARENTS, scene["rotation"],
                                      scene["translation"])
    inputs = {
        "poses": poses, "heads": scene["heads"], "rotation": scene["rotation"], "translation": scene["translation"],
        "target_rotation": 0.3 * torch.randn(frames, joints, 3, generator=generator, dtype=torch.float64),
        "target_translation": 0.2 * torch.randn(frames, 3, generator=generator, dtype=torch.float64),
        "target_pivots": torch.randn(frames, joints, 3, generator=generator, dtype=torch.float64),
        "view_axes": torch.nn.functional.normalize(torch.randn(frames, 3, generator=generator, dtype=torch.float64),
                                                   dim=-1),
        "gaps": 1.0 + 2.0 * torch.rand(max(frames - 1, 0), generator=generator, dtype=torch.float64),
    }
    return {name: value.to(dtype) for name, value in inputs.items()}


PRIOR_ARGS = ("poses", "heads", "rotation", "translation")
PRIOR_OPTIONS = ("target_rotation", "target_translation", "target_pivots", "view_axes", "gaps")


def priors(op, inputs, *, scale=0.7, depth_window=5):
    return op(*(inputs[name] for name in PRIOR_ARGS), **{name: inputs[name] for name in PRIOR_OPTIONS},
              scale=scale, depth_window=depth_window)


def on(scene, device, names=(), dtype=torch.float32):
    """The scene on ``device`` in ``dtype``, ``names`` as leaves that require gradients."""
    return {name: value.to(device=device, dtype=dtype).detach().requires_grad_(name in names)
            for name, value in scene.items()}


@pytest.mark.parametrize("seed", [0, 1])
def test_corrected_poses_match_reference(device, seed):
    scene = random_poses(7, seed)
    ours, theirs = on(scene, device, ("rotation", "translation")), on(scene, "cpu", ("rotation", "translation"),
                                                                   torch.float64)
    out = ops.corrected_poses(ours["bone_transforms"], ours["heads"], PARENTS, ours["rotation"], ours["translation"])
    expected = reference.corrected_poses(theirs["bone_transforms"], theirs["heads"], PARENTS, theirs["rotation"],
                                         theirs["translation"])
    assert out.dtype == torch.float32 and out.device == ours["rotation"].device
    torch.testing.assert_close(out.double().cpu(), expected, rtol=0, atol=2e-5)
    # the reference itself agrees with the model's pointer-jumping torch form
    torch.testing.assert_close(corrected_transforms(scene["bone_transforms"], scene["heads"], ancestor_jumps(PARENTS),
                                                    scene["rotation"], scene["translation"]), expected.detach())
    cotangent = torch.randn(out.shape, generator=torch.Generator().manual_seed(seed + 7), dtype=torch.float64)
    grads = torch.autograd.grad(out, [ours["rotation"], ours["translation"]], cotangent.float().to(device))
    grads_ref = torch.autograd.grad(expected, [theirs["rotation"], theirs["translation"]], cotangent)
    for name, grad, grad_ref in zip(("rotation", "translation"), grads, grads_ref):
        assert grad_ref.abs().max() > 1.0, name
        torch.testing.assert_close(grad.double().cpu(), grad_ref, rtol=1e-4, atol=1e-4 * grad_ref.abs().max().item(),
                                   msg=lambda m, n=name: f"d/d{n}: {m}")


def test_corrected_poses_give_the_given_poses_without_corrections_and_keep_bones_rigid(device):
    scene = on(random_poses(4, 2), device)
    zero = ops.corrected_poses(scene["bone_transforms"], scene["heads"], PARENTS, torch.zeros_like(scene["rotation"]),
                               torch.zeros_like(scene["translation"]))
    torch.testing.assert_close(zero, scene["bone_transforms"], rtol=0, atol=1e-6)
    out = ops.corrected_poses(scene["bone_transforms"], scene["heads"], PARENTS, scene["rotation"],
                              scene["translation"])
    pivots = (out[..., :3, :3] @ scene["heads"][:, :, None])[..., 0] + out[..., :3, 3]
    given = (scene["bone_transforms"][..., :3, :3] @ scene["heads"][:, :, None])[..., 0] + scene["bone_transforms"][
        ..., :3, 3]
    for joint, parent in enumerate(PARENTS):
        if parent >= 0:  # every bone keeps its length
            torch.testing.assert_close((pivots[:, joint] - pivots[:, parent]).norm(dim=-1),
                                       (given[:, joint] - given[:, parent]).norm(dim=-1), rtol=0, atol=1e-5)
        else:  # a root's pivot moves by the frame's offset
            torch.testing.assert_close(pivots[:, joint] - given[:, joint], scene["translation"], rtol=0, atol=1e-5)


def test_corrected_poses_finite_differences(device):
    scene = random_poses(2, 3, parents=PARENTS)
    ours = on(scene, device, ("rotation", "translation"))
    out = ops.corrected_poses(ours["bone_transforms"], ours["heads"], PARENTS, ours["rotation"], ours["translation"])
    cotangent = torch.randn(out.shape, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    grads = torch.autograd.grad(out, [ours["rotation"], ours["translation"]], cotangent.float().to(device))

    def objective(values):
        return (reference.corrected_poses(values["bone_transforms"], values["heads"], PARENTS, values["rotation"],
                                          values["translation"]) * cotangent).sum()

    assert_matches_central_differences(objective, scene, {"rotation": grads[0], "translation": grads[1]},
                                       epsilon=1e-6, rtol=1e-3, relative_atol=1e-4, min_scale=1e-1)


@pytest.mark.parametrize("frames", [1, 2, 4, 9])
def test_pose_priors_match_reference(device, frames):
    # 1-2 frames: no smoothness term; 4: depth moves not averaged (fewer frames than the window); 9: averaged
    inputs = prior_inputs(frames, frames)
    names = ("poses", "rotation", "translation")
    ours, theirs = on(inputs, device, names), on(inputs, "cpu", names, torch.float64)
    out, expected = priors(ops.pose_priors, ours), priors(reference.pose_priors, theirs)
    assert out.shape == (3,) and out.dtype == torch.float32
    torch.testing.assert_close(out.double().cpu(), expected.detach(), rtol=1e-5, atol=1e-6)
    assert (expected[:2] > 0).all() and (expected[2] > 0) == (frames >= 3)
    weights = torch.tensor([0.7, 1.9, -1.3], dtype=torch.float64)
    grads = torch.autograd.grad(out, [ours[n] for n in names], weights.float().to(device))
    grads_ref = torch.autograd.grad(expected, [theirs[n] for n in names], weights)
    for name, grad, grad_ref in zip(names, grads, grads_ref):
        assert grad_ref.abs().max() > 1e-3, name
        torch.testing.assert_close(grad.double().cpu(), grad_ref, rtol=1e-4, atol=1e-5 * grad_ref.abs().max().item(),
                                   msg=lambda m, n=name: f"d/d{n}: {m}")


def test_pose_priors_finite_differences(device):
    inputs = prior_inputs(7, 5)
    names = ("poses", "rotation", "translation")
    ours = on(inputs, device, names)
    weights = torch.tensor([0.7, 1.9, -1.3], dtype=torch.float64)
    grads = torch.autograd.grad(priors(ops.pose_priors, ours), [ours[n] for n in names], weights.float().to(device))

    def objective(values):
        return (priors(reference.pose_priors, values) * weights).sum()

    assert_matches_central_differences(objective, inputs, dict(zip(names, grads)), epsilon=1e-6, rtol=1e-3,
                                       relative_atol=1e-4, min_scale=1e-2)


def test_bad_inputs_are_refused_with_clear_messages():
    scene = on(random_poses(3, 6), "cpu")
    call = lambda parents=PARENTS, **changes: ops.corrected_poses(  # noqa: E731
        *({**scene, **changes}[n] for n in ("bone_transforms", "heads")), parents,
        *({**scene, **changes}[n] for n in ("rotation", "translation")))
    with pytest.raises(TypeError, match="sequence of ints"):
        call(torch.tensor(PARENTS))
    with pytest.raises(ValueError, match="cycle"):
        call([1, 2, 0, -1, 3, 4, -1, 6, 7, 6])
    with pytest.raises(ValueError, match="one per joint"):
        call(PARENTS[:-1])
    with pytest.raises(ValueError, match="rotation must have shape"):
        call(rotation=scene["rotation"][:, :-1])
    with pytest.raises(ValueError, match="corrections only"):
        call(heads=scene["heads"].clone().requires_grad_())
    inputs = on(prior_inputs(6, 7), "cpu")
    with pytest.raises(ValueError, match="odd"):
        priors(ops.pose_priors, inputs, depth_window=4)
    with pytest.raises(ValueError, match="gaps must have shape"):
        priors(ops.pose_priors, {**inputs, "gaps": inputs["gaps"][1:]})
