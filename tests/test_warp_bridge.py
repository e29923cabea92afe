"""The torch -> Warp bridge of every kernel family (``warpavatar._src.warp_utils``): ``to_warp``'s arrays and
``warp_descriptor``'s launch descriptors describe exactly what ``wp.from_torch`` describes, kernels read and write
tensors through them, and layouts that do not fit are refused with a message naming the problem."""

import pytest
import torch
import warp as wp

from warpavatar._src.warp_utils import init_warp, to_warp, torch_stream_scope, warp_descriptor, write_only_descriptor

init_warp()

# (torch shape, torch dtype, Warp dtype or None): scalars, vectors, matrices, 2D arrays of vectors, integer views.
LAYOUTS = [
    ((7,), torch.float32, None),
    ((5, 3), torch.float32, wp.vec3),
    ((4, 6, 3), torch.float32, wp.vec3),
    ((2, 3, 3), torch.float32, wp.mat33),
    ((1, 4, 4), torch.float32, wp.mat44),
    ((9, 2), torch.int32, wp.vec2i),
    ((6, 2), torch.int32, None),
    ((11,), torch.int64, None),
    ((8, 4), torch.int32, None),
    ((3,), torch.float64, None),
    ((4,), torch.int32, wp.uint32),
]


def _random(shape, dtype, device):
    if dtype.is_floating_point:
        return torch.rand(shape, dtype=dtype, device=device) + 0.25
    return torch.randint(1, 1000, shape, dtype=dtype, device=device)


@pytest.mark.parametrize("shape, torch_dtype, warp_dtype", LAYOUTS)
def test_views_match_from_torch(device, shape, torch_dtype, warp_dtype):
    tensor = _random(shape, torch_dtype, device)
    reference = wp.from_torch(tensor, dtype=warp_dtype, requires_grad=False)
    array = to_warp(tensor, warp_dtype)
    assert (array.dtype, array.shape, array.strides, array.ptr) == (
        reference.dtype, reference.shape, reference.strides, reference.ptr)
    assert str(array.device) == str(reference.device)
    descriptor = warp_descriptor(tensor, warp_dtype)
    assert bytes(descriptor) == bytes(reference.__ctype__())
    # The same descriptor twice (the cached layout) and for a view at an offset.
    assert bytes(warp_descriptor(tensor, warp_dtype)) == bytes(descriptor)
    tail = tensor[1:]
    assert bytes(warp_descriptor(tail, warp_dtype)) == bytes(
        wp.from_torch(tail, dtype=warp_dtype, requires_grad=False).__ctype__())


@wp.kernel(enable_backward=False)
def _scaled_sum_kernel(points: wp.array(dtype=wp.vec3), weights: wp.array2d(dtype=wp.float32),
                       out: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    out[i] = points[i] * (weights[i, 0] + 2.0 * weights[i, 1])


def test_kernels_read_and_write_through_descriptors(device):
    points = torch.randn(37, 3, device=device)
    weights = torch.rand(37, 2, device=device)
    out = torch.full((37, 3), -7.0, device=device)
    with torch_stream_scope(device):
        wp.launch(_scaled_sum_kernel, dim=37,
                  inputs=[warp_descriptor(points, wp.vec3), warp_descriptor(weights)],
                  outputs=[warp_descriptor(out, wp.vec3)])
    torch.testing.assert_close(out, points * (weights[:, :1] + 2.0 * weights[:, 1:]))
    # to_warp's arrays write the tensor too, and keep it alive after the tensor's last name is gone.
    array = to_warp(torch.zeros(5, 3, device=device), wp.vec3)
    array.fill_(wp.vec3(1.5, -2.0, 3.0))
    assert array._tensor.sum().item() == pytest.approx(5 * 2.5)


def test_bad_layouts_are_refused():
    with pytest.raises(ValueError, match="contiguous"):
        warp_descriptor(torch.zeros(4, 6)[:, ::2])
    with pytest.raises(ValueError, match=r"last dimensions must be \[3\]"):
        warp_descriptor(torch.zeros(4, 4), wp.vec3)
    with pytest.raises(ValueError, match=r"last dimensions must be \[3\]"):
        to_warp(torch.zeros(4, 2), wp.vec3)
    with pytest.raises(TypeError, match="torch.float64 tensor as Warp vec3f"):
        warp_descriptor(torch.zeros(4, 3, dtype=torch.float64), wp.vec3)
    with pytest.raises(TypeError, match="torch.int32 tensor as Warp float32"):
        to_warp(torch.zeros(4, dtype=torch.int32), wp.float32)
    with pytest.raises(TypeError, match="cannot read torch.complex64 tensors"):
        warp_descriptor(torch.zeros(4, dtype=torch.complex64))
    # to_warp copies a non-contiguous tensor instead.
    strided = torch.arange(24.0).reshape(4, 6)[:, ::2]
    assert to_warp(strided).numpy().tolist() == strided.tolist()


@wp.kernel
def _weighted_square_kernel(values: wp.array(dtype=wp.vec3), weight: float, squares: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    v = values[i]
    squares[i] = weight * wp.cw_mul(v, v)


def test_adjoint_launch_with_write_only_outputs(device):
    # The forward outputs an adjoint launch replays may all share one element: the gradients are those of full
    # output arrays, bit for bit, and equal to the closed form 2 w v * d squares.
    count, weight = 53, 1.75
    values = torch.randn(count, 3, device=device)
    grad_squares = torch.randn(count, 3, device=device)
    gradients = []
    for write_only in (False, True):
        grad_values = torch.zeros(count, 3, device=device)
        sink = torch.empty(3, device=device)
        squares = (write_only_descriptor(sink, count, wp.vec3) if write_only
                   else warp_descriptor(torch.empty(count, 3, device=device), wp.vec3))
        with torch_stream_scope(device):
            wp.launch(_weighted_square_kernel, dim=count, inputs=[warp_descriptor(values, wp.vec3), weight],
                      outputs=[squares], adj_inputs=[warp_descriptor(grad_values, wp.vec3), 0.0],
                      adj_outputs=[warp_descriptor(grad_squares, wp.vec3)], adjoint=True)
        gradients.append(grad_values)
    assert torch.equal(gradients[0], gradients[1])
    torch.testing.assert_close(gradients[1], 2.0 * weight * values * grad_squares)
    with pytest.raises(ValueError, match="at least 12 bytes, got 8"):
        write_only_descriptor(torch.empty(2, device=device), count, wp.vec3)
