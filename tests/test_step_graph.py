"""The capture-ready paths: the rasterizer with a fixed intersection capacity (no host read), the training step
without host synchronizations (and, where CUDA exists, replayed from a CUDA graph), and the playback
:class:`~warpavatar.model.playback.Player`."""

from __future__ import annotations

import pytest
import torch

from warpavatar import _torch_impl as reference
from warpavatar import ops
from tests.test_splat import make_scene, random_cotangents, render_and_grad


def _rasterize_with(capacity):
    def rasterize(*args, **kwargs):
        return ops.rasterize_gaussians(*args, intersection_capacity=capacity, **kwargs)
    return rasterize


@pytest.mark.parametrize("seed, sh_degree", [(3, None), (4, 2)])
def test_capacity_matches_exact_buffers(seed, sh_degree):
    """Images, gradients and densification gradients are identical with a capacity that holds every pair."""
    scene, sizes = make_scene(seed, gaussian_count=300, width=48, height=40, sh_degree=sh_degree)
    cotangents = random_cotangents(sizes, "cpu", seed)
    exact = render_and_grad(ops.rasterize_gaussians, scene, sizes, cotangents, densify=True)
    *_, info = ops.rasterize_gaussians(scene["means"], scene["quats"], scene["scales"], scene["opacities"],
                                       scene["colors"], scene["K"], scene["world_to_camera"], sizes["width"],
                                       sizes["height"], sh_degree=sh_degree, return_info=True)
    pair_count = ops.rasterizer_status(info)
    assert pair_count > 300
    *_, reference_info = reference.rasterize_gaussians(
        scene["means"], scene["quats"], scene["scales"], scene["opacities"], scene["colors"], scene["K"],
        scene["world_to_camera"], sizes["width"], sizes["height"], sh_degree=sh_degree, return_info=True)
    assert ops.rasterizer_status(reference_info) == pair_count
    for capacity in (pair_count, 2 * pair_count + 17):
        outputs, grads, densify = render_and_grad(_rasterize_with(capacity), scene, sizes, cotangents, densify=True)
        assert all(torch.equal(a, b) for a, b in zip(outputs, exact[0]))
        assert grads.keys() == exact[1].keys()
        assert all(torch.equal(grads[name], exact[1][name]) for name in grads)
        assert torch.equal(densify, exact[2])


def test_capacity_overflow_is_flagged_not_fatal():
    scene, sizes = make_scene(5, gaussian_count=300, width=48, height=40)
    args = [scene[k] for k in ("means", "quats", "scales", "opacities", "colors", "K", "world_to_camera")]
    image, _, _, info = ops.rasterize_gaussians(*args, sizes["width"], sizes["height"], return_info=True)
    needed = ops.rasterizer_status(info)
    short, _, _, short_info = ops.rasterize_gaussians(*args, sizes["width"], sizes["height"], return_info=True,
                                                      intersection_capacity=needed // 2)
    assert ops.rasterizer_status(short_info) == needed  # the count needed, past the capacity
    assert torch.isfinite(short).all() and not torch.equal(short, image)
    # non-finite input: the exact path raises at once, the capped path flags it on the device
    args[0] = args[0].clone()
    args[0][7, 1] = float("nan")
    with pytest.raises(ValueError, match="non-finite values in means"):
        ops.rasterize_gaussians(*args, sizes["width"], sizes["height"])
    *_, bad_info = ops.rasterize_gaussians(*args, sizes["width"], sizes["height"], return_info=True,
                                           intersection_capacity=2 * needed)
    with pytest.raises(ValueError, match="non-finite values in means"):
        ops.rasterizer_status(bad_info)
    with pytest.raises(ValueError, match="intersection_capacity"):
        ops.rasterize_gaussians(*args, sizes["width"], sizes["height"], intersection_capacity=0)
