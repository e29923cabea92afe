"""Reused launch commands (``warpavatar.kernels.launch``) and the rasterizer's direct sort and scan calls
(``warpavatar._src.warp_utils``): the same results as ``wp.launch`` and ``warp.utils`` on random inputs, call
after call with new arrays, sizes and scalars, on every device; no argument kept alive by a command."""

import gc
from typing import Any
import weakref

import pytest
import torch
import warp as wp

from warpavatar._src import warp_utils
from warpavatar._src.warp_utils import (inclusive_scan, init_warp, radix_sort_pairs, to_warp, torch_stream_scope,
                                        warp_descriptor)
from warpavatar.kernels import launch as launch_module
from warpavatar.kernels.launch import launch, reused_commands

init_warp()


@wp.kernel
def _affine_kernel(points: wp.array(dtype=wp.vec3), weights: wp.array2d(dtype=wp.float32), scale: float,
                   offset: int, out: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    out[i] = scale * points[i] * (weights[i, 0] + 2.0 * weights[i, 1]) + wp.vec3(float(offset), 0.0, 0.0)


@wp.kernel
def _grid_kernel(values: wp.array2d(dtype=wp.float32), out: wp.array2d(dtype=wp.float32)):
    i, j = wp.tid()
    out[i, j] = values[i, j] * float(i + 1) - float(j)


def _affine_args(count, device, scale, offset, *, as_arrays=False):
    points = torch.randn(count, 3, device=device)
    weights = torch.rand(count, 2, device=device) + 0.5
    out = torch.full((count, 3), -9.0, device=device)
    wrap = (lambda t, dtype=None: to_warp(t, dtype)) if as_arrays else warp_descriptor
    expected = scale * points * (weights[:, :1] + 2.0 * weights[:, 1:])
    expected[:, 0] += offset
    return [wrap(points, wp.vec3), wrap(weights), scale, offset], [wrap(out, wp.vec3)], out, expected


def test_reused_launches_match_wp_launch_call_after_call(device):
    # New arrays, sizes and scalars each call, descriptors and wp.arrays mixed: the reused command's results equal
    # wp.launch's bit for bit, and one command serves them all.
    reused_commands().clear()
    for call, (count, scale, offset) in enumerate([(37, 1.5, 2), (37, 1.5, 2), (91, -0.75, 2), (5, 3.25, -4)]):
        inputs, outputs, out, expected = _affine_args(count, device, scale, offset, as_arrays=call % 2 == 1)
        reference = torch.full_like(out, -9.0)
        with torch_stream_scope(device):
            launch(_affine_kernel, dim=count, inputs=inputs, outputs=outputs)
            wp.launch(_affine_kernel, dim=count, inputs=inputs, outputs=[warp_descriptor(reference, wp.vec3)])
        assert torch.equal(out, reference)
        torch.testing.assert_close(out, expected)
    assert sum(key[0] is _affine_kernel for key in reused_commands()) == 1
    # Two-dimensional launches, their extent changing.
    for rows, columns in ((4, 7), (9, 3)):
        values = torch.rand(rows, columns, device=device)
        out = torch.zeros(rows, columns, device=device)
        with torch_stream_scope(device):
            launch(_grid_kernel, dim=(rows, columns), inputs=[warp_descriptor(values)], outputs=[warp_descriptor(out)])
        rows_scale = torch.arange(1, rows + 1, device=device, dtype=torch.float32)[:, None]
        columns_offset = torch.arange(columns, device=device, dtype=torch.float32)[None]
        torch.testing.assert_close(out, values * rows_scale - columns_offset)


def test_a_command_keeps_no_argument_alive(device):
    # Two calls (the recording one and a reused one): once the caller drops its tensors, nothing holds them.
    reused_commands().clear()
    inputs, outputs, out, _ = _affine_args(64, device, 0.5, 1)
    with torch_stream_scope(device):
        launch(_affine_kernel, dim=64, inputs=inputs, outputs=outputs)
        launch(_affine_kernel, dim=64, inputs=inputs, outputs=outputs)
    if device.startswith("cuda"):
        torch.cuda.synchronize()
    alive = [weakref.ref(argument._tensor) for argument in inputs + outputs if hasattr(argument, "_tensor")]
    del inputs, outputs, out
    gc.collect()
    assert len(alive) == 3 and all(reference() is None for reference in alive)


@wp.kernel
def _scaled_sine_kernel(values: wp.array(dtype=wp.float32), weight: float, sines: wp.array(dtype=wp.float32)):
    i = wp.tid()
    sines[i] = weight * wp.sin(values[i])


def test_adjoint_launches_match_wp_launch(device):
    for count, weight in ((53, 1.75), (20, -0.5)):
        values = torch.randn(count, device=device)
        grad_sines = torch.randn(count, device=device)
        gradients = []
        for launcher in (launch, wp.launch):
            grad_values = torch.zeros(count, device=device)
            with torch_stream_scope(device):
                launcher(_scaled_sine_kernel, dim=count, inputs=[warp_descriptor(values), weight],
                         outputs=[warp_descriptor(torch.empty(count, device=device))],
                         adj_inputs=[warp_descriptor(grad_values), 0.0], adj_outputs=[warp_descriptor(grad_sines)],
                         adjoint=True)
            gradients.append(grad_values)
        assert torch.equal(gradients[0], gradients[1])
        torch.testing.assert_close(gradients[0], weight * torch.cos(values) * grad_sines)


def test_an_array_argument_must_stay_an_array(device):
    inputs, outputs, _, _ = _affine_args(8, device, 1.0, 0)
    with torch_stream_scope(device):
        launch(_affine_kernel, dim=8, inputs=inputs, outputs=outputs)
        with pytest.raises(TypeError, match="argument 0 of .* must be an array or None"):
            launch(_affine_kernel, dim=8, inputs=[3.0] + inputs[1:], outputs=outputs)
        launch(_affine_kernel, dim=0, inputs=[3.0] + inputs[1:], outputs=outputs)  # nothing to run: no check


@wp.kernel
def _generic_double_kernel(values: wp.array(dtype=Any), out: wp.array(dtype=Any)):
    i = wp.tid()
    out[i] = values[i] + values[i]


@pytest.mark.parametrize("reuse", [True, False])
def test_generic_kernels_resolve_their_overload_every_call(device, reuse, monkeypatch):
    # Generic kernels, and every kernel with reuse switched off, go through wp.launch (no command recorded).
    monkeypatch.setattr(launch_module, "REUSE_COMMANDS", reuse)
    reused_commands().clear()
    if not reuse:
        inputs, outputs, out, expected = _affine_args(9, device, 2.0, 1)
        with torch_stream_scope(device):
            launch(_affine_kernel, dim=9, inputs=inputs, outputs=outputs)
        torch.testing.assert_close(out, expected)
    for dtype in (torch.float32, torch.int32, torch.float32):
        values = (torch.rand(12, device=device) * 100).to(dtype)
        out = torch.zeros_like(values)
        with torch_stream_scope(device):
            launch(_generic_double_kernel, dim=12, inputs=[to_warp(values)], outputs=[to_warp(out)])
        assert torch.equal(out, values + values)
    assert not reused_commands()


@pytest.mark.parametrize("native", [True, False])
def test_sort_and_scan_match_torch(device, native, monkeypatch):
    if not native:
        monkeypatch.setattr(warp_utils, "_native_core", lambda: None)  # the public warp.utils path
    generator = torch.Generator().manual_seed(3)
    for count in (1, 257, 4000):
        # Few distinct keys: the stable order of equal keys is checked too.
        keys = torch.randint(0, 37, (2 * count,), generator=generator).to(torch.float32).to(device)
        records = torch.stack([torch.arange(2 * count), torch.randint(0, 9, (2 * count,), generator=generator)],
                              dim=1).to(torch.int32).to(device)
        expected_keys, order = torch.sort(keys[:count], stable=True)
        expected_records = records[:count][order]
        with torch_stream_scope(device):
            radix_sort_pairs(keys, records, count, begin_bit=0, end_bit=31)
        assert torch.equal(keys[:count], expected_keys)
        assert torch.equal(records[:count], expected_records)
        # The inclusive sum of the records' second column, read in place (stride 2).
        sums = torch.full((count,), -1, dtype=torch.int32, device=device)
        with torch_stream_scope(device):
            inclusive_scan(records[:, 1], sums, stride=2)
        assert torch.equal(sums, torch.cumsum(records[:count, 1], 0).to(torch.int32))
        # Integer keys with one-word values, on a bit range.
        int_keys = torch.randint(0, 1 << 12, (2 * count,), generator=generator, dtype=torch.int32).to(device)
        ids = torch.arange(2 * count, dtype=torch.int32, device=device)
        expected_int, int_order = torch.sort(int_keys[:count], stable=True)
        with torch_stream_scope(device):
            radix_sort_pairs(int_keys, ids, count, begin_bit=0, end_bit=12)
        assert torch.equal(int_keys[:count], expected_int)
        assert torch.equal(ids[:count], int_order.to(torch.int32))
    with pytest.raises(ValueError, match="2 \\* 5 elements"):
        radix_sort_pairs(torch.zeros(6, device=device), torch.zeros(10, dtype=torch.int32, device=device), 5,
                         begin_bit=0, end_bit=31)
    with pytest.raises(ValueError, match="int32"):
        inclusive_scan(torch.zeros(4, device=device), torch.zeros(4, dtype=torch.int32, device=device))
    with pytest.raises(ValueError, match="4 values 2 apart do not fit"):
        inclusive_scan(torch.ones(6, dtype=torch.int32, device=device)[1:], torch.zeros(4, dtype=torch.int32,
                                                                                       device=device), stride=2)


@wp.kernel
def _optional_weights_kernel(values: wp.array(dtype=wp.float32), weights: wp.array(dtype=wp.float32),
                             out: wp.array(dtype=wp.float32)):
    i = wp.tid()
    weight = float(1.0)
    if weights.shape[0] > 0:
        weight = weights[i]
    out[i] = weight * values[i]


def test_optional_arrays_may_be_left_out_call_to_call(device):
    reused_commands().clear()
    values = torch.rand(16, device=device) + 0.5
    weights = torch.rand(16, device=device) + 0.5
    for use_weights in (False, True, False, True):
        out = torch.zeros(16, device=device)
        with torch_stream_scope(device):
            launch(_optional_weights_kernel, dim=16,
                   inputs=[warp_descriptor(values), warp_descriptor(weights) if use_weights else None],
                   outputs=[warp_descriptor(out)])
        torch.testing.assert_close(out, values * weights if use_weights else values)
