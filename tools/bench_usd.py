"""USD export benchmark: time, file size and peak memory of writing an animated Gaussian avatar.

``python tools/bench_usd.py [--gaussians 40000] [--frames 300] [--quick]`` writes a synthetic animation
(random Gaussians drifting and rotating) with :class:`warpavatar.io.usd.GaussianUsdWriter` in each layout,
and in the particlefield layout once more with a single save at the end (``flush_every = frames``) to show
what the incremental saves buy. Each row runs in a fresh Python process so its peak resident memory
(``VmHWM``) is its own; ``RSS growth`` is that peak minus the resident size just before writing (after
imports, usd-core's one-time plug-in loading and the static arrays). The time covers the ``write_frame``
calls and ``close()`` only, not the generation of the synthetic frames. It is a CPU benchmark: ``device`` is
ignored.

Also a mode of ``tools/bench_kernels.py`` through :func:`run`.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time

__all__ = ["run", "main"]


def _resident_mib() -> float:
    with open("/proc/self/statm") as stream:
        return int(stream.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def _peak_resident_mib() -> float:
    """This process's peak resident size. VmHWM belongs to the current address space; ru_maxrss would also
    count the parent's size at fork time, which Linux carries across exec."""
    try:
        with open("/proc/self/status") as stream:
            for line in stream:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # KiB on Linux


def _write_once(path: str, layout: str, gaussian_count: int, frame_count: int, flush_every: int | None) -> dict:
    """Write one synthetic animation and report its cost (runs inside the child process)."""
    import numpy as np

    from warpavatar.io.usd import GaussianUsdWriter

    rng = np.random.default_rng(0)
    sh_degree = 3
    opacities = rng.uniform(0.05, 1.0, size=gaussian_count).astype(np.float32)
    sh_coeffs = (rng.normal(size=(gaussian_count, (sh_degree + 1) ** 2, 3)) * 0.3).astype(np.float32)
    base_positions = rng.normal(size=(gaussian_count, 3)).astype(np.float32)
    velocities = (rng.normal(size=(gaussian_count, 3)) * 0.01).astype(np.float32)
    base_quats = rng.normal(size=(gaussian_count, 4)).astype(np.float32)
    base_scales = np.exp(rng.normal(-4.0, 0.5, size=(gaussian_count, 3))).astype(np.float32)
    # usd-core loads its plug-ins and schema registry on first use (~100 MiB): do it before measuring.
    from pxr import Usd, UsdGeom, UsdVol

    warm_up = Usd.Stage.CreateInMemory()
    UsdVol.ParticleField3DGaussianSplat.Define(warm_up, "/WarmUp/Splats")
    UsdGeom.Points.Define(warm_up, "/WarmUp/Points")
    del warm_up
    resident_before = _resident_mib()

    elapsed = 0.0
    start = time.perf_counter()
    writer = GaussianUsdWriter(path, layout=layout, gaussian_count=gaussian_count, sh_degree=sh_degree,
                               opacities=opacities, sh_coeffs=sh_coeffs, fps=30.0, flush_every=flush_every)
    elapsed += time.perf_counter() - start
    with writer:
        for frame in range(frame_count):
            positions = base_positions + frame * velocities
            quats = base_quats + np.float32(0.01 * frame)
            scales = base_scales * np.float32(1.0 + 0.001 * frame)
            start = time.perf_counter()
            writer.write_frame(frame, positions=positions, orientations=quats, scales=scales)
            elapsed += time.perf_counter() - start
        start = time.perf_counter()
        writer.close()
        elapsed += time.perf_counter() - start
    peak = _peak_resident_mib()
    return {
        "write_s": elapsed,
        "file_mib": os.path.getsize(path) / 2**20,
        "peak_rss_mib": peak,
        "rss_growth_mib": peak - resident_before,
        "flush_every": writer.flush_every,
    }


def _measure(layout: str, gaussian_count: int, frame_count: int, flush_every: int | None) -> dict:
    """Run :func:`_write_once` in a fresh interpreter and return its numbers."""
    with tempfile.TemporaryDirectory(prefix="bench_usd_") as folder:
        path = os.path.join(folder, f"bench_{layout}.usdc")
        command = [sys.executable, os.path.abspath(__file__), "--child", path, layout, str(gaussian_count),
                   str(frame_count), str(flush_every or 0)]
        result = subprocess.run(command, check=True, capture_output=True, text=True)
    return json.loads(result.stdout.strip().splitlines()[-1])


def run(device: str = "cpu", quick: bool = False, *, gaussian_count: int | None = None,
        frame_count: int | None = None) -> list[dict]:
    """Benchmark rows (one per layout / save policy) for ``tools/bench_kernels.py``; ``device`` is ignored.

    Args:
        device: ignored (USD export runs on the CPU).
        quick: 2,000 Gaussians x 20 frames instead of 40,000 x 300.
        gaussian_count: override the number of Gaussians.
        frame_count: override the number of frames.
    """
    del device
    gaussian_count = gaussian_count or (2_000 if quick else 40_000)
    frame_count = frame_count or (20 if quick else 300)
    rows = []
    for layout, flush_every, saves in (("particlefield", None, "incremental"), ("points", None, "incremental"),
                                       ("particlefield", frame_count, "once at close")):
        numbers = _measure(layout, gaussian_count, frame_count, flush_every)
        rows.append({
            "layout": layout,
            "saves": f"{saves} (every {numbers['flush_every']} frames)" if saves == "incremental" else saves,
            "gaussians": gaussian_count,
            "frames": frame_count,
            "write s": numbers["write_s"],
            "ms/frame": 1e3 * numbers["write_s"] / frame_count,
            "file MiB": numbers["file_mib"],
            "peak RSS MiB": numbers["peak_rss_mib"],
            "RSS growth MiB": numbers["rss_growth_mib"],
        })
    return rows


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "--child":
        path, layout, gaussian_count, frame_count, flush_every = argv[1:6]
        numbers = _write_once(path, layout, int(gaussian_count), int(frame_count), int(flush_every) or None)
        print(json.dumps(numbers))
        return 0
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--gaussians", type=int, default=None, help="Gaussian count (default 40000, quick 2000)")
    parser.add_argument("--frames", type=int, default=None, help="frame count (default 300, quick 20)")
    parser.add_argument("--quick", action="store_true", help="small sizes: checks that the benchmark runs")
    args = parser.parse_args(argv)
    from bench_common import markdown_table

    rows = run("cpu", args.quick, gaussian_count=args.gaussians, frame_count=args.frames)
    print(markdown_table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
