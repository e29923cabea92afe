"""View-dependent colour benchmark: ``python tools/bench_kernels.py shading [--device cuda:0] [--quick]``.

Times :func:`warpavatar.ops.view_colors` (one fused Warp kernel forward, one backward) against the op-by-op
plain-torch code it replaced (:func:`warpavatar._torch_impl.view_colors`) on N = 10k, 90k and 500k Gaussians
(``--quick``: 2k) at SH degrees 1 and 3: random unit quaternions, coefficients of either sign, a shading origin
off the cloud's centre. Rows give the median time of the forward (``torch.no_grad``) and of forward +
backward (``torch.autograd.grad`` with respect to means, both quaternions and the coefficients), and the
torch operators each dispatches (forward + backward, counted with ``bench_avatar``'s op counter).
"""

from __future__ import annotations


import torch

from bench_common import time_function

from warpavatar import _torch_impl as reference
from warpavatar import ops

__all__ = ["run", "make_gaussians"]


def make_gaussians(count: int, degree: int, device: str, *, seed: int = 0) -> dict:
    """Random posed Gaussians for ``view_colors`` (float32 on ``device``, leaves that require gradients)."""
    generator = torch.Generator().manual_seed(seed)
    unit = torch.nn.functional.normalize
    values = {
        "means": torch.randn(count, 3, generator=generator),
        "quats": unit(torch.randn(count, 4, generator=generator), dim=-1),
        "canonical_quats": unit(torch.randn(count, 4, generator=generator), dim=-1),
        "sh_coefficients": 0.5 * torch.randn(count, (degree + 1) ** 2, 3, generator=generator),
    }
    gaussians = {name: value.to(device).requires_grad_() for name, value in values.items()}
    gaussians["origin"] = torch.tensor([0.3, -2.0, 1.0], device=device)
    return gaussians


def _op_count(function) -> float:
    from bench_avatar import _OpCounter

    counter = _OpCounter()
    with counter:
        function()
    return sum(counter.ops.values())


def run(device: str, quick: bool) -> list[dict]:
    sizes = (2_000,) if quick else (10_000, 90_000, 500_000)
    warmup, repeats = (1, 3) if quick else (3, 15)
    rows = []
    for count in sizes:
        for degree in (1, 3):
            gaussians = make_gaussians(count, degree, device)
            leaves = [gaussians[name] for name in ("means", "quats", "canonical_quats", "sh_coefficients")]
            cotangent = torch.randn(count, 3, generator=torch.Generator().manual_seed(1)).to(device)
            for name, function in (("torch op-by-op", reference.view_colors), ("warp fused", ops.view_colors)):
                def forward(function=function):
                    with torch.no_grad():
                        function(*gaussians.values(), sh_degree=degree)

                def forward_backward(function=function):
                    colors = function(*gaussians.values(), sh_degree=degree)
                    torch.autograd.grad(colors, leaves, cotangent)

                rows.append({"N": count, "degree": degree, "impl": name,
                             "fwd_ms": time_function(forward, device=device, warmup=warmup, repeats=repeats),
                             "fwd_bwd_ms": time_function(forward_backward, device=device, warmup=warmup,
                                                         repeats=repeats),
                             "torch_ops": _op_count(forward_backward)})
    return rows
