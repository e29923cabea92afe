"""The skinning field evaluated at the active grid points only (``--field-cells active``): the same loss and
gradients as evaluating every grid point."""

import dataclasses

import pytest
import torch

from warpavatar.fit.presets import preset
from warpavatar.fit.skinning_field_stage import SkinningStage
from warpavatar.model.skinning_field import VoxelSkinningField


def _field(device, joints=6, seed=0):
    torch.manual_seed(seed)
    field = VoxelSkinningField(torch.tensor([-0.4, -0.2, 0.0]), torch.tensor([0.4, 0.25, 1.7]), joints, cells=24,
                               min_cells=5, hidden=24, layers=2).to(device)
    return field


def _points(count, device, seed, spread=1.15):
    generator = torch.Generator().manual_seed(seed)
    low, high = torch.tensor([-0.4, -0.2, 0.0]), torch.tensor([0.4, 0.25, 1.7])
    centre, half = (low + high) / 2, (high - low) / 2 * spread  # some points outside the box (border clamping)
    return (centre + (torch.rand(count, 3, generator=generator) * 2 - 1) * half).to(device)


@pytest.mark.parametrize("dilation", [0, 1])
@pytest.mark.parametrize("seed", [0, 1])
def test_cells_read_by_holds_every_grid_point_that_interpolation_reads(device, dilation, seed):
    field = _field(device)
    points = _points(300, device, seed)
    cells = field.cells_read_by(points, dilation=dilation)
    assert cells.dtype == torch.long and bool((cells[1:] > cells[:-1]).all())
    assert 0 < cells.numel() < field.cell_count
    grid = field.grid_weights().detach().requires_grad_()
    field.weights(points, grid).mul(torch.rand(points.shape[0], field.joint_count, device=device)).sum().backward()
    read = torch.nonzero(grid.grad.reshape(field.cell_count, -1).abs().sum(1) > 0).squeeze(1)
    assert read.numel() > 0 and bool(torch.isin(read, cells).all())
    # and a grid changed everywhere else gives the same weights
    changed = grid.detach().clone().reshape(field.cell_count, -1)
    outside = torch.ones(field.cell_count, dtype=torch.bool, device=device)
    outside[cells] = False
    changed[outside] = torch.rand(int(outside.sum()), field.joint_count, device=device)
    torch.testing.assert_close(field.weights(points, changed.reshape(grid.shape)), field.weights(points, grid.detach()),
                               rtol=0, atol=0)


def test_dilated_cells_cover_points_moved_by_less_than_a_cell(device):
    field = _field(device)
    points = _points(200, device, 3, spread=0.9)
    cells = field.cells_read_by(points, dilation=1)
    cell_size = (field.bbox_max - field.bbox_min) / (torch.tensor(field.grid_shape[::-1], device=device) - 1)
    generator = torch.Generator().manual_seed(4)
    moved = points + (torch.rand(points.shape, generator=generator).to(device) * 2 - 1) * 0.95 * cell_size
    assert bool(torch.isin(field.cells_read_by(moved, dilation=0), cells).all())


def _stage(device, mode, field):
    class Skeleton:
        heads = [[0.0, 0.0, 0.1 + 0.25 * j] for j in range(6)]
        tails = [[0.0, 0.0, 0.35 + 0.25 * j] for j in range(6)]
        parents = [-1, 0, 1, 2, 3, 4]
    config = dataclasses.replace(preset("quick"), field_cells=mode, field_cells_every=10, field_warmup_batch=0)
    return SkinningStage(field, Skeleton, config, extent=1.0)


def test_active_cells_give_the_loss_and_gradients_of_the_whole_grid(device):
    points = _points(400, device, 5, spread=0.95)
    losses, grads = {}, {}
    for mode in ("all", "active"):
        field = _field(device, seed=7)
        stage = _stage(device, mode, field)
        stage.begin_step(0, points, train_field=True)
        grid = stage.grid(0, train_field=True)
        weights = field.weights(points, grid)
        target = torch.softmax(torch.sin(points @ torch.ones(3, 6, device=device) * torch.arange(6, device=device)), -1)
        bone = field.bone_loss(stage.bone_samples, stage.bone_sample_index, grid)
        loss = ((weights - target) ** 2).sum() + bone
        loss.backward()
        losses[mode] = loss.detach()
        grads[mode] = [p.grad.detach().clone() for p in field.parameters()]
        if mode == "active":
            assert 0 < stage.active_cells < field.cell_count
    torch.testing.assert_close(losses["active"], losses["all"], rtol=1e-6, atol=1e-6)
    for active, whole in zip(grads["active"], grads["all"]):
        torch.testing.assert_close(active, whole, rtol=1e-4, atol=1e-6)


def test_active_cells_are_chosen_again_on_schedule_and_on_count_change(device):
    field = _field(device)
    stage = _stage(device, "active", field)
    points = _points(100, device, 6, spread=0.5)
    stage.begin_step(0, points, train_field=True)
    first = (stage.active_cells, stage.graph_key())
    stage.begin_step(5, points[:50], train_field=True)  # fewer Gaussians: chosen again, fewer cells
    assert stage.active_cells < first[0] and stage.graph_key() == first[1]  # same buffers (capacity kept)
    more = _points(2000, device, 8, spread=1.0)
    stage.begin_step(6, more, train_field=True)  # more cells than the capacity: new buffers
    assert stage.active_cells > first[0] and stage.graph_key() != first[1]
    chosen = stage._cells_chosen
    stage.begin_step(7, more, train_field=True)
    assert stage._cells_chosen == chosen
    stage.forget_cells()
    stage.begin_step(8, more, train_field=True)
    assert stage._cells_chosen == (8, more.shape[0])
    stage.begin_step(20, more, train_field=True)  # field_cells_every = 10
    assert stage._cells_chosen == (20, more.shape[0])


def test_field_cells_option_is_checked():
    from warpavatar.fit.config import FitConfig

    with pytest.raises(ValueError, match="field_cells must be"):
        FitConfig.from_flat({"field_cells": "some"})
    with pytest.raises(ValueError, match="field-cells-every"):
        FitConfig.from_flat({"field_cells_every": 0})
