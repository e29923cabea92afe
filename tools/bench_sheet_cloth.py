"""Triangle-mesh cloth benchmark: ``python tools/bench_kernels.py sheet_cloth [--device cuda:0] [--quick]``, or
``python tools/bench_sheet_cloth.py [--device cpu] [--vertices 2000] [--substeps 8] [--quick]`` on its own.

Garment: a skirt (:func:`make_skirt`), an open cylinder of radius 0.25 m and length 0.5 m triangulated as a grid
of about ``V`` vertices (2k by default; ``--quick``: 500), its top ring pinned and moved a little each frame (as
skinning moves a waistband), against 20 body capsules (a torso capsule inside the skirt and 19 limb capsules
around it). :class:`warpavatar.sim.SheetCloth` with an areal density of 0.2 kg/m^2 and its membrane at 0.9 and its
bending at 0.5 of their bounds; a frame is 1/30 s, split into each row's number of substeps (8, 20 and 40; the
cloth is built with ``max_substep`` one substep, so its bounds hold: 20 substeps is the default ``max_substep``
of 1/600 s).

Rows time, per frame (median), three kernel launches a substep:

* ``rollout frame, no grad``: :meth:`SheetCloth.rollout` of 8 frames under ``torch.no_grad``, per frame (what
  playing the cloth costs);
* ``training window forward+backward``: a rollout of 4 frames with autograd, then the gradient of a loss of every
  frame's positions with respect to the five parameters, the initial state and the pins, per frame.

The issue's targets: a rollout frame at most 0.2 ms on a GPU and 20 ms on 2 CPU cores. Warp runs a CPU kernel on
one thread; ``OMP_NUM_THREADS=1`` keeps torch's thread pool from competing with it on a small machine.
"""

from __future__ import annotations

import argparse
import math
import sys

import torch

from bench_common import markdown_table, time_function

from warpavatar.sim import Capsules, SheetCloth

__all__ = ["run", "make_skirt", "make_scene"]

FRAME_INTERVAL = 1.0 / 30.0


def make_skirt(rows: int, columns: int, *, radius: float = 0.25, length: float = 0.5, noise: float = 0.0,
               seed: int = 0, top: float = 0.0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """An open cylinder (a skirt) of ``rows x columns`` vertices: ``(positions [V, 3], faces [T, 3], ring [columns])``.

    The axis is ``+z`` and the top ring (row 0, at height ``top``) comes first; each grid quad is split into two
    triangles along alternating diagonals, and every vertex moves by ``noise`` times the ring spacing in a random
    direction (float32 positions, int64 faces and ring ids).
    """
    generator = torch.Generator().manual_seed(seed)
    row, column = torch.meshgrid(torch.arange(rows), torch.arange(columns), indexing="ij")
    angle = 2.0 * math.pi * column.reshape(-1).double() / columns
    height = top - length * row.reshape(-1).double() / max(rows - 1, 1)
    positions = torch.stack([radius * angle.cos(), radius * angle.sin(), height], dim=1)
    spacing = 2.0 * math.pi * radius / columns
    positions = positions + noise * spacing * torch.randn(positions.shape, generator=generator, dtype=torch.float64)
    i, j = torch.meshgrid(torch.arange(rows - 1), torch.arange(columns), indexing="ij")
    i, j = i.reshape(-1), j.reshape(-1)
    a, b = i * columns + j, i * columns + (j + 1) % columns
    c, d = a + columns, b + columns
    even = ((i + j) % 2 == 0)[:, None]
    first = torch.where(even, torch.stack([a, c, b], 1), torch.stack([a, c, d], 1))
    second = torch.where(even, torch.stack([b, c, d], 1), torch.stack([a, d, b], 1))
    faces = torch.cat([first, second])
    return positions.float(), faces, torch.arange(columns)


def make_scene(vertex_count: int, device: str, *, max_substep: float = 1.0 / 600.0, seed: int = 0):
    """The benchmark's skirt of about ``vertex_count`` vertices as a :class:`SheetCloth` on ``device``, its rest
    state, its ring's rest positions, and 20 capsules."""
    generator = torch.Generator().manual_seed(seed)
    radius, length = 0.25, 0.5
    spacing = math.sqrt(2 * math.pi * radius * length / vertex_count)
    columns = max(3, round(2 * math.pi * radius / spacing))
    rows = max(2, round(vertex_count / columns))
    positions, faces, ring = make_skirt(rows, columns, radius=radius, length=length, noise=0.05, seed=seed, top=1.0)
    cloth = SheetCloth(positions.to(device), faces.to(device), ring.to(device), max_substep=max_substep,
                       stretch_stiffness=0.9, shear_stiffness=0.9, bend_stiffness=0.5)
    start = torch.cat([torch.tensor([[0.0, 0.0, 0.45]]), 0.6 * (torch.rand(19, 3, generator=generator) - 0.5)
                       + torch.tensor([0.0, 0.0, 0.7])])
    end = torch.cat([torch.tensor([[0.0, 0.0, 1.0]]), start[1:] + 0.3 * torch.randn(19, 3, generator=generator)])
    capsule_radius = torch.cat([torch.tensor([0.2]), 0.03 + 0.04 * torch.rand(19, generator=generator)])
    capsules = Capsules(start.to(device), end.to(device), capsule_radius.to(device))
    return cloth, cloth.rest_state(), positions[ring].to(device), capsules


def _frames_of(capsules: Capsules, frame_count: int) -> Capsules:
    return Capsules(capsules.segment_start.expand(frame_count, -1, -1),
                    capsules.segment_end.expand(frame_count, -1, -1), capsules.radius.expand(frame_count, -1))


def run(device: str, quick: bool, *, vertex_count: int | None = None, substep_counts=None) -> list[dict]:
    """Benchmark rows (see the module docstring)."""
    vertex_count = vertex_count or (500 if quick else 2000)
    substep_counts = substep_counts or ((20,) if quick else (8, 20, 40))
    warmup, repeats = (1, 3) if quick else ((5, 30) if device.startswith("cuda") else (2, 5))
    rows = []
    for substeps in substep_counts:
        cloth, state, ring, capsules = make_scene(vertex_count, device, max_substep=FRAME_INTERVAL / substeps)
        frame_count = 8
        sway = torch.linspace(0, 0.02, frame_count, device=device)[:, None, None] * torch.tensor([1.0, 0.0, 0.0],
                                                                                                device=device)
        pins = ring[None] + sway
        frame_capsules = _frames_of(capsules, frame_count)

        def rollout(frames=frame_count, pins=pins, frame_capsules=frame_capsules, substeps=substeps):
            return cloth.rollout(state, pins[:frames], FRAME_INTERVAL, capsules=Capsules(
                frame_capsules.segment_start[:frames], frame_capsules.segment_end[:frames],
                frame_capsules.radius[:frames]), substeps=substeps)

        with torch.no_grad():
            ms = time_function(rollout, device=device, warmup=warmup, repeats=repeats) / frame_count
        rows.append(_row(cloth, f"rollout frame, no grad ({substeps} substeps)", ms, substeps))

        window = 4
        pin_leaf = pins[:window].clone().requires_grad_()
        initial = type(state)(state.positions.clone().requires_grad_(), state.velocities.clone().requires_grad_())
        inputs = [*cloth.parameters(), pin_leaf, initial.positions, initial.velocities]

        def train_window(substeps=substeps):
            positions, _ = cloth.rollout(initial, pin_leaf, FRAME_INTERVAL, capsules=Capsules(
                frame_capsules.segment_start[:window], frame_capsules.segment_end[:window],
                frame_capsules.radius[:window]), substeps=substeps)
            return torch.autograd.grad((positions * positions).sum(), inputs)

        ms = time_function(train_window, device=device, warmup=warmup, repeats=repeats) / window
        rows.append(_row(cloth, f"training window forward+backward, per frame ({substeps} substeps)", ms, substeps))
    return rows


def _row(cloth: SheetCloth, op: str, ms: float, substeps: int) -> dict:
    return {"vertices": cloth.vertex_count, "triangles": cloth.mesh.triangle_count, "hinges": cloth.mesh.hinge_count,
            "op": op, "ms": ms, "ms per substep": ms / substeps, "threads": torch.get_num_threads()}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cuda:0" if torch.cuda.is_available() else "cpu",
                        help="torch device to run on (default: cuda:0 when available, else cpu)")
    parser.add_argument("--vertices", type=int, default=None, help="skirt vertices (default 2000; --quick 500)")
    parser.add_argument("--substeps", type=int, nargs="+", default=None,
                        help="substeps per frame to time (default 8 20 40; --quick 20)")
    parser.add_argument("--quick", action="store_true", help="a small skirt and few repetitions")
    args = parser.parse_args(argv)
    if args.vertices is not None and args.vertices < 12:
        parser.error(f"--vertices must be at least 12, got {args.vertices}")
    if args.substeps is not None and min(args.substeps) < 1:
        parser.error(f"--substeps must be >= 1, got {args.substeps}")
    rows = run(args.device, args.quick, vertex_count=args.vertices, substep_counts=args.substeps)
    print(markdown_table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
