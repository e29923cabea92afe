"""Gaussians bound to triangles (kernels/triangle_binding.py, warpavatar.model.triangle_gaussians): values and
gradients against the plain-torch reference and central differences, rigid and stretched meshes, binding, and the
per-triangle density control."""

import math

import pytest
import torch
import trimesh

from conftest import assert_matches_central_differences
from warpavatar import _torch_impl as reference
from warpavatar import ops
from warpavatar.geometry import quat_to_matrix
from warpavatar.model.triangle_gaussians import SPLIT_SCALE_DIVISOR, TriangleGaussians, triangle_areas


def _random_binding(generator, *, vertex_count=12, face_count=10, count=40, dtype=torch.float32):
    vertices = torch.randn(vertex_count, 3, generator=generator, dtype=torch.float64)
    faces = torch.stack([torch.randperm(vertex_count, generator=generator)[:3] for _ in range(face_count)])
    rest_area = triangle_areas(vertices, faces) * (0.5 + torch.rand(face_count, generator=generator,
                                                                    dtype=torch.float64))
    ids = torch.randint(0, face_count, (count,), generator=generator)
    bary = torch.rand(count, 3, generator=generator, dtype=torch.float64) + 0.05
    bary = bary / bary.sum(1, keepdim=True)
    offsets = 0.1 * torch.randn(count, generator=generator, dtype=torch.float64)
    quats = torch.randn(count, 4, generator=generator, dtype=torch.float64)
    log_scales = torch.randn(count, 3, generator=generator, dtype=torch.float64) - 3.0
    floats = {"vertices": vertices, "barycentrics": bary, "offsets": offsets, "local_quats": quats,
              "local_log_scales": log_scales}
    return {name: value.to(dtype) for name, value in floats.items()}, faces, rest_area.to(dtype), ids


def _pose(module, inputs, faces, rest_area, ids):
    return module.pose_triangle_gaussians(inputs["vertices"], faces, rest_area, ids, inputs["barycentrics"],
                                          inputs["offsets"], inputs["local_quats"], inputs["local_log_scales"])


def _on(device, inputs, faces, rest_area, ids):
    return {k: v.to(device) for k, v in inputs.items()}, faces.to(device), rest_area.to(device), ids.to(device)


def test_pose_matches_the_reference(device):
    inputs, faces, rest_area, ids = _on(device, *_random_binding(torch.Generator().manual_seed(1)))
    got = _pose(ops, inputs, faces, rest_area, ids)
    want = _pose(reference, inputs, faces, rest_area, ids)
    for name, a, b in zip(("means", "quats", "log_scales"), got, want):
        assert a.device == b.device and a.dtype == torch.float32
        torch.testing.assert_close(a, b, atol=2e-5, rtol=1e-5, msg=lambda m, n=name: f"{n}: {m}")


def test_gradients_match_the_reference(device):
    generator = torch.Generator().manual_seed(2)
    inputs, faces, rest_area, ids = _on(device, *_random_binding(generator))
    names = list(inputs)
    cotangents = [torch.randn(ids.shape[0], width, generator=generator).to(device) for width in (3, 4, 3)]

    def grads(module, dtype):
        leaves = {k: v.detach().to(dtype).requires_grad_(True) for k, v in inputs.items()}
        outputs = _pose(module, leaves, faces, rest_area.to(dtype), ids)
        loss = sum((o * c.to(dtype)).sum() for o, c in zip(outputs, cotangents))
        return dict(zip(names, torch.autograd.grad(loss, [leaves[n] for n in names])))

    got, want = grads(ops, torch.float32), grads(reference, torch.float64)
    for name in names:
        scale = want[name].abs().max().item()
        torch.testing.assert_close(got[name].double(), want[name], atol=1e-5 * max(scale, 1.0), rtol=1e-4,
                                   msg=lambda m, n=name: f"d/d{n}: {m}")


def test_gradients_match_central_differences():
    generator = torch.Generator().manual_seed(3)
    inputs, faces, rest_area, ids = _random_binding(generator, vertex_count=6, face_count=4, count=6,
                                                    dtype=torch.float64)
    cotangents = [torch.randn(ids.shape[0], width, generator=generator, dtype=torch.float64)
                  for width in (3, 4, 3)]

    def objective(values):
        outputs = _pose(reference, values, faces, rest_area, ids)
        return float(sum((o * c).sum() for o, c in zip(outputs, cotangents)))

    leaves = {k: v.float().requires_grad_(True) for k, v in inputs.items()}
    outputs = _pose(ops, leaves, faces, rest_area.float(), ids)
    loss = sum((o * c.float()).sum() for o, c in zip(outputs, cotangents))
    analytic = dict(zip(leaves, torch.autograd.grad(loss, list(leaves.values()))))
    assert_matches_central_differences(objective, inputs, analytic, epsilon=1e-6, rtol=1e-3, relative_atol=1e-4,
                                       min_scale=1e-3)


def _rotation(generator) -> torch.Tensor:
    q = torch.randn(4, generator=generator, dtype=torch.float64)
    return quat_to_matrix(q / q.norm())


def test_a_rigid_motion_of_the_mesh_moves_the_gaussians_rigidly(device):
    generator = torch.Generator().manual_seed(4)
    inputs, faces, rest_area, ids = _random_binding(generator)
    rotation, translation = _rotation(generator).float(), torch.randn(3, generator=generator)
    moved = dict(inputs, vertices=inputs["vertices"] @ rotation.T + translation)
    means, quats, log_scales = _pose(ops, *_on(device, inputs, faces, rest_area, ids))
    moved_means, moved_quats, moved_log_scales = _pose(ops, *_on(device, moved, faces, rest_area, ids))
    rotation, translation = rotation.to(device), translation.to(device)
    torch.testing.assert_close(moved_means, means @ rotation.T + translation, atol=2e-5, rtol=0)
    turned = quat_to_matrix(quats / quats.norm(dim=1, keepdim=True))
    moved_turned = quat_to_matrix(moved_quats / moved_quats.norm(dim=1, keepdim=True))
    torch.testing.assert_close(moved_turned, rotation @ turned, atol=2e-5, rtol=0)
    torch.testing.assert_close(moved_quats.norm(dim=1), quats.norm(dim=1), atol=1e-5, rtol=0)
    torch.testing.assert_close(moved_log_scales, log_scales, atol=1e-5, rtol=0)


def test_a_stretched_mesh_stretches_its_gaussians(device):
    generator = torch.Generator().manual_seed(5)
    inputs, faces, rest_area, ids = _random_binding(generator)
    rest_area = triangle_areas(inputs["vertices"], faces)  # the given vertices are the rest shape
    inputs["offsets"] = torch.zeros_like(inputs["offsets"])
    factor = 1.7
    means, _, log_scales = _pose(ops, *_on(device, inputs, faces, rest_area, ids))
    stretched = dict(inputs, vertices=inputs["vertices"] * factor)
    big_means, _, big_log_scales = _pose(ops, *_on(device, stretched, faces, rest_area, ids))
    torch.testing.assert_close(log_scales, inputs["local_log_scales"].to(device), atol=1e-5, rtol=0)
    torch.testing.assert_close(big_log_scales, log_scales + math.log(factor), atol=1e-5, rtol=0)
    torch.testing.assert_close(big_means, means * factor, atol=1e-5, rtol=0)


def test_bad_ids_are_refused_on_the_host_and_poisoned_on_the_device(device):
    inputs, faces, rest_area, ids = _random_binding(torch.Generator().manual_seed(6), count=5)
    with pytest.raises(ValueError, match="triangle_ids must hold ids"):
        _pose(ops, inputs, faces, rest_area, ids + 100)
    with pytest.raises(ValueError, match="faces must hold ids"):
        _pose(ops, inputs, faces + 100, rest_area, ids)
    with pytest.raises(TypeError, match="float32"):
        _pose(ops, {k: v.double() for k, v in inputs.items()}, faces, rest_area, ids)
    if device != "cpu":  # not checked on the host: NaN marks the bad rows
        bad = ids.clone()
        bad[2] = 1000
        means, quats, log_scales = _pose(ops, *_on(device, inputs, faces, rest_area, bad))
        assert torch.isnan(means[2]).all() and torch.isnan(quats[2]).all() and torch.isnan(log_scales[2]).all()
        assert torch.isfinite(means[[0, 1, 3, 4]]).all()


def test_no_gaussians_is_empty_work(device):
    inputs, faces, rest_area, ids = _random_binding(torch.Generator().manual_seed(7), count=0)
    inputs = {k: v.to(device).requires_grad_(True) for k, v in inputs.items()}
    outputs = _pose(ops, inputs, faces.to(device), rest_area.to(device), ids.to(device))
    assert [list(o.shape) for o in outputs] == [[0, 3], [0, 4], [0, 3]]
    sum(o.sum() for o in outputs).backward()
    assert float(inputs["vertices"].grad.abs().sum()) == 0.0


def _sphere(subdivisions=2):
    mesh = trimesh.creation.icosphere(subdivisions=subdivisions, radius=0.3)
    return torch.as_tensor(mesh.vertices, dtype=torch.float32), torch.as_tensor(mesh.faces, dtype=torch.int64)


def test_closest_triangles_match_the_reference(device):
    vertices, faces = _sphere(1)
    points = 0.4 * torch.randn(200, 3)
    got_ids, got_weights = ops.closest_triangles(points.to(device), vertices.to(device), faces.to(device))
    want_ids, want_weights = reference.closest_triangles(points, vertices, faces)
    assert got_ids.dtype == torch.int64 and bool((got_ids >= 0).all())

    def closest(ids, weights):
        return (weights.cpu()[:, :, None] * vertices[faces[ids.cpu()]]).sum(1)

    # the same closest point (its triangle may differ where a shared edge or corner is closest)
    torch.testing.assert_close(closest(got_ids, got_weights), closest(want_ids, want_weights), atol=1e-5, rtol=0)
    assert bool((got_weights >= -1e-6).all()) and torch.allclose(got_weights.sum(1), torch.ones(200, device=device))
    far_ids, _ = ops.closest_triangles(points.to(device) + 10.0, vertices.to(device), faces.to(device),
                                       max_distance=1.0)
    assert bool((far_ids == -1).all())


def _surface_gaussians(vertices, faces, count, generator, *, offset=0.004):
    """Gaussians inside random triangles of a mesh, a little off its surface, with random rotations and scales."""
    ids = torch.randint(0, faces.shape[0], (count,), generator=generator)
    bary = torch.rand(count, 3, generator=generator) + 0.2
    bary = bary / bary.sum(1, keepdim=True)
    corners = vertices[faces[ids]]
    normal = torch.linalg.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0], dim=1)
    normal = normal / normal.norm(dim=1, keepdim=True)
    points = (bary[:, :, None] * corners).sum(1) + offset * (2 * torch.rand(count, 1, generator=generator) - 1) * normal
    quats = torch.randn(count, 4, generator=generator)
    quats = quats / quats.norm(dim=1, keepdim=True)
    scales = 0.002 + 0.01 * torch.rand(count, 3, generator=generator)
    return points, quats, scales


def test_bind_then_pose_at_rest_gives_back_the_gaussians(device):
    vertices, faces = _sphere()
    points, quats, scales = _surface_gaussians(vertices, faces, 300, torch.Generator().manual_seed(8))
    bound = TriangleGaussians.bind(points.to(device), quats.to(device), scales.to(device), (vertices, faces))
    means, posed_quats, posed_scales = bound.posed(bound.rest_vertices)
    torch.testing.assert_close(means.cpu(), points, atol=5e-5, rtol=0)
    turned = quat_to_matrix(posed_quats / posed_quats.norm(dim=1, keepdim=True)).cpu()
    torch.testing.assert_close(turned, quat_to_matrix(quats), atol=1e-5, rtol=0)
    torch.testing.assert_close(posed_scales.cpu(), scales, atol=1e-6, rtol=1e-5)
    assert int(bound.gaussians_per_triangle().sum()) == 300
    # a trimesh.Trimesh binds the same way
    mesh = trimesh.Trimesh(vertices.numpy(), faces.numpy(), process=False)
    again = TriangleGaussians.bind(points.to(device), quats.to(device), scales.to(device), mesh)
    torch.testing.assert_close(again.posed(again.rest_vertices)[0].cpu(), points, atol=5e-5, rtol=0)


def test_posed_gaussians_follow_a_deformed_mesh_and_pass_gradients(device):
    vertices, faces = _sphere(1)
    points, quats, scales = _surface_gaussians(vertices, faces, 50, torch.Generator().manual_seed(9))
    bound = TriangleGaussians.bind(points.to(device), quats.to(device), scales.to(device), (vertices, faces))
    posed_vertices = (bound.rest_vertices * torch.tensor([1.0, 1.5, 1.0], device=device)).requires_grad_(True)
    means, posed_quats, posed_scales = bound.posed(posed_vertices)
    (means.sum() + posed_quats.sum() + posed_scales.sum()).backward()
    for name in ("barycentric_logits", "offsets", "local_quats", "local_log_scales"):
        assert getattr(bound, name).grad is not None and bool(getattr(bound, name).grad.abs().sum() > 0), name
    assert bool(posed_vertices.grad.abs().sum() > 0)
    # the centres stay on their triangles' stretched surface (a softmax keeps the weights in the triangle)
    assert bool((bound.barycentrics() > 0).all())


def test_densify_clones_and_splits_under_a_cap_per_triangle(device):
    vertices, faces = _sphere(1)
    generator = torch.Generator().manual_seed(10)
    points, quats, scales = _surface_gaussians(vertices, faces, 120, generator)
    bound = TriangleGaussians.bind(points.to(device), quats.to(device), scales.to(device), (vertices, faces))
    before = bound.gaussians_per_triangle().clone()
    old = {n: getattr(bound, n).detach().clone() for n in ("barycentric_logits", "offsets", "local_quats",
                                                           "local_log_scales")}
    old_ids = bound.triangle_ids.clone()
    old_means = bound.posed(bound.rest_vertices)[0].detach()
    selected = torch.rand(120, generator=generator).to(device) < 0.6
    split = torch.rand(120, generator=generator).to(device) < 0.5
    cap = int(before.max())  # some triangles are already full
    source = bound.densify(selected, split=split, max_per_triangle=cap)
    after = bound.gaussians_per_triangle()
    assert int(after.max()) <= cap and bound.count == source.shape[0]
    assert bool((after >= before).all()) and bound.count > 120
    assert torch.equal(source[:120], torch.arange(120, device=device))
    assert torch.equal(bound.triangle_ids, old_ids[source])  # every new Gaussian on its parent's triangle
    added = source[120:]
    assert bool(selected[added].all())
    cloned, split_added = added[~split[added]], 120 + torch.nonzero(split[added]).squeeze(1)
    new_cloned = 120 + torch.nonzero(~split[added]).squeeze(1)
    for name, value in old.items():
        torch.testing.assert_close(getattr(bound, name).detach()[new_cloned], value[cloned])
    split_parents = source[split_added]
    torch.testing.assert_close(bound.local_log_scales.detach()[split_added],
                               old["local_log_scales"][split_parents] - math.log(SPLIT_SCALE_DIVISOR))
    torch.testing.assert_close(bound.local_log_scales.detach()[split_parents],
                               old["local_log_scales"][split_parents] - math.log(SPLIT_SCALE_DIVISOR))
    # the two children sit on either side of the parent, along the triangle
    means = bound.posed(bound.rest_vertices)[0].detach()
    first, second = means[split_parents], means[split_added]
    assert bool(((first - second).norm(dim=1) > 1e-4).all())
    midpoint = 0.5 * (first + second)
    assert float((midpoint - old_means[split_parents]).norm(dim=1).median()) < 2e-3
    # a full triangle takes nothing more
    again = bound.densify(torch.ones(bound.count, dtype=torch.bool, device=device), max_per_triangle=cap)
    assert int(bound.gaussians_per_triangle().max()) <= cap and again.shape[0] == bound.count


def test_prune_keeps_the_last_gaussian_of_each_triangle(device):
    vertices, faces = _sphere(1)
    points, quats, scales = _surface_gaussians(vertices, faces, 200, torch.Generator().manual_seed(11))
    bound = TriangleGaussians.bind(points.to(device), quats.to(device), scales.to(device), (vertices, faces))
    occupied = bound.gaussians_per_triangle() > 0
    ids_before = bound.triangle_ids.clone()
    priority = torch.rand(200, device=device)
    kept = bound.prune(torch.zeros(200, dtype=torch.bool, device=device), priority=priority)
    assert torch.equal(bound.gaussians_per_triangle() > 0, occupied)
    assert int(bound.gaussians_per_triangle().max()) == 1
    for triangle, index in zip(bound.triangle_ids.tolist(), kept.tolist()):  # each triangle's highest priority
        members = torch.nonzero(ids_before == triangle).squeeze(1)
        assert index == int(members[priority[members].argmax()])
    bound.prune(torch.zeros(bound.count, dtype=torch.bool, device=device), keep_last_per_triangle=False)
    assert bound.count == 0
