"""How ``warpavatar-fit-many`` scales with the GPUs of one host: the same batch of fits on 1, 2, 4 ... GPUs.

    python tools/bench_fit_many.py --subjects A B ... -o OUT [--fits N] [--gpus 1,2,4] [--gpus-per-fit 1,0.5]
        [--cpus-per-fit C] [--device cuda|cpu] [--warm-up-steps S] [-- FIT OPTIONS ...]

The batch is ``--fits`` fits: the subject folders in turn, then copies of them (links named ``<name>-2``,
``<name>-3``, ...) until there are N. ``warpavatar-fit-many`` applies one configuration to every subject, so a copy
is the same fit as its original (the same seed): the same work, which is what a throughput benchmark wants.
Each GPU count K (times each ``--gpus-per-fit``) runs the whole batch on a fresh local Ray instance that sees the
host's first K GPUs (``CUDA_VISIBLE_DEVICES``, ``num_gpus``), from scratch (``--force``) into
``OUT/runs/<K>gpu-<G>/``; anything after ``--`` goes to every fit (``-- --iterations 4000``). Before them an
untimed warm-up fit of ``--warm-up-steps`` steps fills the kernel cache, so no row pays for compiling.

Printed per row: wall time of the batch (Ray's start excluded), the median per-fit time (the fit's own, as the
subject's result records it), fits an hour, how many distinct GPUs the fits ran on (by the UUIDs their results
record), the GPUs' mean utilisation while the batch ran (``nvidia-smi``, sampled in a thread) and the scaling
efficiency: ``wall(K0) * K0 / (wall(K) * K)`` against the row of fewest GPUs with the same ``--gpus-per-fit`` (1.0:
K GPUs finish K times sooner), and the speed-up over one fit a GPU at the same K. Everything, with each fit's GPU
and times, is written to ``OUT/bench_fit_many.json`` (through a temporary file and a rename).

``--device cpu`` (where no GPU is): K stands for K fit slots, a Ray instance of K x ``--cpus-per-fit`` CPUs and no
GPUs; tests/test_bench_fit_many.py runs it so with tiny fits.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import json
import os
import shutil
import socket
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

from bench_common import markdown_table

RESULT_NAME = "bench_fit_many.json"


def host_gpus() -> list[dict]:
    """The host's GPUs as ``nvidia-smi`` lists them (``index``, ``uuid``, ``name``), [] without it."""
    if shutil.which("nvidia-smi") is None:
        return []
    try:
        lines = subprocess.run(["nvidia-smi", "--query-gpu=index,uuid,name", "--format=csv,noheader"],
                               capture_output=True, text=True, timeout=60, check=True).stdout.splitlines()
    except (OSError, subprocess.SubprocessError):
        return []
    gpus = []
    for line in lines:
        fields = [field.strip() for field in line.split(",")]
        if len(fields) >= 3:
            gpus.append({"index": fields[0], "uuid": fields[1], "name": ",".join(fields[2:])})
    return gpus


class UtilisationSampler:
    """Samples every GPU's utilisation [%] and memory in use [MiB] with ``nvidia-smi`` in a thread, every
    ``interval`` seconds, while active; :meth:`mean_utilisation` averages a window of the samples."""

    def __init__(self, *, interval: float = 0.5):
        self.interval = interval
        self.samples: list[tuple[float, str, float, float]] = []  # (time, uuid, utilisation %, memory MiB)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def __enter__(self):
        if shutil.which("nvidia-smi") is not None:
            self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=30)
        return False

    def _run(self) -> None:
        query = ["nvidia-smi", "--query-gpu=uuid,utilization.gpu,memory.used", "--format=csv,noheader,nounits"]
        while not self._stop.is_set():
            now = time.time()
            try:
                lines = subprocess.run(query, capture_output=True, text=True, timeout=30).stdout.splitlines()
            except (OSError, subprocess.SubprocessError):
                lines = []
            for line in lines:
                fields = [field.strip() for field in line.split(",")]
                try:
                    self.samples.append((now, fields[0], float(fields[1]), float(fields[2])))
                except (IndexError, ValueError):
                    continue
            self._stop.wait(max(0.0, self.interval - (time.time() - now)))

    def window(self, start: float, end: float, uuids: set[str]) -> list[tuple[float, str, float, float]]:
        """The samples of the GPUs ``uuids`` taken between ``start`` and ``end`` (time.time())."""
        return [sample for sample in self.samples if start <= sample[0] <= end and sample[1] in uuids]

    def mean_utilisation(self, start: float, end: float, uuids: set[str]) -> float | None:
        """Mean utilisation [%] of the GPUs ``uuids`` between ``start`` and ``end``; None without samples."""
        values = [sample[2] for sample in self.window(start, end, uuids)]
        return round(statistics.fmean(values), 1) if values else None

    def peak_memory(self, start: float, end: float, uuids: set[str]) -> float | None:
        """Largest memory in use [MiB] of one of the GPUs ``uuids`` between ``start`` and ``end``."""
        values = [sample[3] for sample in self.window(start, end, uuids)]
        return max(values) if values else None


def batch_subjects(folders: list[Path], fits: int, root: Path) -> list[Path]:
    """``fits`` subject links in ``root``: one per folder in turn, then copies (``<name>-2``, ...) until there are
    ``fits``; each link points at its (absolute) folder."""
    root.mkdir(parents=True, exist_ok=True)
    links, used = [], set()
    for number in range(fits):
        folder = folders[number % len(folders)].absolute()
        copy = number // len(folders) + 1
        name = folder.name if copy == 1 else f"{folder.name}-{copy}"
        while name in used:
            name += "x"
        used.add(name)
        link = root / name
        if link.is_symlink() or link.exists():
            if not link.is_symlink() or Path(os.readlink(link)) != folder:
                raise ValueError(f"{link}: exists and is not a link to {folder}; give another -o")
        else:
            link.symlink_to(folder, target_is_directory=True)
        links.append(link)
    return links


def run_configuration(subjects: list[Path], output: Path, *, gpus: int, gpus_per_fit: float, cpus_per_fit: float,
                      device: str, fit_options: list[str], host_gpu_ids: list[str],
                      sampler: UtilisationSampler | None) -> dict:
    """Fit ``subjects`` with ``warpavatar-fit-many`` on a fresh local Ray instance of ``gpus`` GPUs (on the CPU:
    ``gpus`` fit slots); the row of the table, with each fit's result under ``"fits"``."""
    import logging

    import ray

    from warpavatar.batch import SUMMARY_NAME
    from warpavatar.cli import fit_many
    cuda = device == "cuda"
    saved = os.environ.get("CUDA_VISIBLE_DEVICES")
    if cuda:  # the Ray instance (its raylet and workers) sees the first K GPUs
        os.environ["CUDA_VISIBLE_DEVICES"] = ",".join(host_gpu_ids[:gpus])
    started = time.time()
    try:
        ray.init(num_cpus=None if cuda else max(1, round(gpus * cpus_per_fit)), num_gpus=gpus if cuda else 0,
                 include_dashboard=False, log_to_driver=False, logging_level=logging.WARNING)
    finally:
        if saved is None:
            os.environ.pop("CUDA_VISIBLE_DEVICES", None)
        else:
            os.environ["CUDA_VISIBLE_DEVICES"] = saved
    ray_seconds = time.time() - started
    try:
        argv = [*map(str, subjects), "-o", str(output), "--force", "--no-progress", "--device", device,
                "--gpus-per-fit", f"{gpus_per_fit if cuda else 0:g}", "--cpus-per-fit", f"{cpus_per_fit:g}",
                *fit_options]
        start = time.time()
        status = fit_many.main(argv)
        end = time.time()
    finally:
        ray.shutdown()
    summary = output / f"{SUMMARY_NAME}.json"
    results = json.loads(summary.read_text(encoding="utf-8"))["subjects"] if status in (0, 1) else []
    fits = [{"subject": result["subject"], "status": result["status"], "attempts": result.get("attempts"),
             "fit_seconds": result.get("fit_seconds"), "wall_seconds": result.get("wall_seconds"),
             "gpu": (result.get("gpu") or {}).get("uuid"), "device": result.get("device")} for result in results]
    uuids = {fit["gpu"] for fit in fits if fit["gpu"]}
    fit_seconds = [fit["fit_seconds"] for fit in fits if fit["fit_seconds"] is not None]
    wall = end - start
    return {"gpus": gpus, "gpus_per_fit": gpus_per_fit if cuda else 0, "fits": len(subjects),
            "done": sum(fit["status"] == "done" for fit in fits), "status": status,
            "wall_s": round(wall, 1), "ray_start_s": round(ray_seconds, 1),
            "per_fit_s": round(statistics.median(fit_seconds), 1) if fit_seconds else None,
            "fits_per_hour": round(len(subjects) / wall * 3600, 1) if wall > 0 else None,
            "gpus_used": len(uuids) if cuda else None,
            "gpu_util_pct": sampler.mean_utilisation(start, end, uuids) if sampler and uuids else None,
            "gpu_peak_mib": sampler.peak_memory(start, end, uuids) if sampler and uuids else None,
            "fit_results": fits}


def add_efficiency(rows: list[dict]) -> None:
    """Each row's scaling efficiency (against the row of fewest GPUs with the same GPUs a fit) and its speed-up
    over one fit a GPU at the same GPU count (where that row exists)."""
    for row in rows:
        same_share = [other for other in rows if other["gpus_per_fit"] == row["gpus_per_fit"] and other["wall_s"]]
        base = min(same_share, key=lambda other: other["gpus"], default=None)
        row["efficiency"] = (round(base["wall_s"] * base["gpus"] / (row["wall_s"] * row["gpus"]), 3)
                             if base and row["wall_s"] else None)
        whole = [other for other in rows if other["gpus"] == row["gpus"] and other["gpus_per_fit"] == 1
                 and other["wall_s"]]
        row["vs_one_fit_a_gpu"] = round(whole[0]["wall_s"] / row["wall_s"], 3) if whole and row["wall_s"] else None


def _numbers(text: str, kind):
    try:
        values = [kind(value) for value in text.split(",") if value.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from None
    if not values or any(value < 0 for value in values):
        raise argparse.ArgumentTypeError(f"expected comma-separated non-negative numbers, got {text!r}")
    return values


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--subjects", nargs="+", type=Path, default=None, metavar="FOLDER",
                        help="subject folders (train/ inside) or video folders (default: the demo subject)")
    parser.add_argument("-o", "--output", type=Path, required=True, help="output folder of the benchmark")
    parser.add_argument("--fits", type=int, default=None, metavar="N",
                        help="fits in the batch: the subjects in turn, then copies (default: one per subject)")
    parser.add_argument("--gpus", type=lambda text: _numbers(text, int), default=None, metavar="K,K,...",
                        help="GPU counts to run the batch on (default: 1,2,4 as far as the host has GPUs; on the "
                             "CPU 1,2 fit slots)")
    parser.add_argument("--gpus-per-fit", type=lambda text: _numbers(text, float), default=[1.0],
                        metavar="G,G,...", help="GPUs a fit asks Ray for, each value a row per GPU count "
                                                "(default: 1; 0.5 shares a GPU between two fits)")
    parser.add_argument("--cpus-per-fit", type=float, default=None, metavar="C",
                        help="CPU cores a fit asks Ray for (default: the host's cores over the most fits at a time, "
                             "1 to 4)")
    parser.add_argument("--device", choices=("cuda", "cpu"), default=None,
                        help="where the fits run (default: cuda when nvidia-smi lists GPUs, else cpu)")
    parser.add_argument("--warm-up-steps", type=int, default=600, metavar="S",
                        help="steps of the untimed fit that fills the kernel cache first (default: %(default)s; "
                             "0: none)")
    parser.add_argument("--sample-every", type=float, default=0.5, metavar="SECONDS",
                        help="nvidia-smi sampling interval (default: %(default)s)")
    parser.add_argument("fit_options", nargs=argparse.REMAINDER,
                        help="after --: options of every fit (warpavatar-fit's)")
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    fit_options = args.fit_options[1:] if args.fit_options[:1] == ["--"] else args.fit_options
    from warpavatar import data
    from warpavatar.io.output_files import write_json_atomic

    folders = args.subjects or [data.demo_subject_path()]
    for folder in folders:
        if not folder.is_dir():
            parser.error(f"--subjects: {folder} is not a folder")
    fits = args.fits if args.fits is not None else len(folders)
    if fits < 1:
        parser.error(f"--fits must be >= 1, got {fits}")
    gpus_on_host = host_gpus()
    device = args.device or ("cuda" if gpus_on_host else "cpu")
    visible = os.environ.get("CUDA_VISIBLE_DEVICES")
    host_gpu_ids = ([entry.strip() for entry in visible.split(",") if entry.strip()] if visible is not None
                    else [gpu["index"] for gpu in gpus_on_host])
    if device == "cuda":
        if not host_gpu_ids:
            parser.error("--device cuda: nvidia-smi lists no GPU on this host (give --device cpu)")
        counts = args.gpus or [count for count in (1, 2, 4) if count <= len(host_gpu_ids)]
        if max(counts) > len(host_gpu_ids) or min(counts) < 1:
            parser.error(f"--gpus {','.join(map(str, counts))}: this host has {len(host_gpu_ids)} GPUs")
        shares = args.gpus_per_fit
        for share in shares:
            if share <= 0 or (share > 1 and share != round(share)) or share > min(counts):
                parser.error(f"--gpus-per-fit {share:g}: a fit takes a fraction of a GPU or whole GPUs, at most "
                             f"the fewest of --gpus ({min(counts)})")
    else:
        counts, shares = args.gpus or [1, 2], [0.0]
        if min(counts) < 1:
            parser.error("--gpus: the fit slot counts must be >= 1")
    most_at_once = max(count / share if share else count for count in counts for share in shares)
    cpus_per_fit = args.cpus_per_fit or float(max(1, min(4, (os.cpu_count() or 1) // max(1, int(most_at_once)))))

    output = args.output
    output.mkdir(parents=True, exist_ok=True)
    subjects = batch_subjects(folders, fits, output / "subjects")
    print(f"{fits} fits of {', '.join(folder.name for folder in folders)} on {device}; GPU counts "
          f"{','.join(map(str, counts))}, {','.join(f'{share:g}' for share in shares)} GPUs and {cpus_per_fit:g} "
          f"CPUs a fit; fit options: {' '.join(fit_options) or '(preset defaults)'}", flush=True)
    rows = []
    sampling = UtilisationSampler(interval=args.sample_every) if device == "cuda" else contextlib.nullcontext()
    with sampling as sampler:
        if args.warm_up_steps:
            warm = run_configuration(subjects[:1], output / "runs" / "warm-up", gpus=1, gpus_per_fit=1.0,
                                     cpus_per_fit=cpus_per_fit, device=device,
                                     fit_options=[*fit_options, "--iterations", str(args.warm_up_steps)],
                                     host_gpu_ids=host_gpu_ids, sampler=None)
            print(f"warm-up: one fit of {args.warm_up_steps} steps in {warm['wall_s']} s (kernel cache filled)",
                  flush=True)
        for share in shares:
            for count in counts:
                label = f"{count}gpu-{share:g}" if device == "cuda" else f"{count}slot"
                row = run_configuration(subjects, output / "runs" / label, gpus=count, gpus_per_fit=share,
                                        cpus_per_fit=cpus_per_fit, device=device, fit_options=fit_options,
                                        host_gpu_ids=host_gpu_ids, sampler=sampler)
                rows.append(row)
                print(f"{label}: {row['done']}/{row['fits']} done in {row['wall_s']} s", flush=True)
    add_efficiency(rows)
    columns = ("gpus", "gpus_per_fit", "fits", "done", "wall_s", "per_fit_s", "fits_per_hour", "gpus_used",
               "gpu_util_pct", "gpu_peak_mib", "efficiency", "vs_one_fit_a_gpu")
    table = [{column: ("" if row[column] is None else row[column]) for column in columns} for row in rows]
    print(markdown_table(table))
    record = {"date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
              "host": socket.gethostname(), "host_gpus": gpus_on_host, "device": device,
              "command": [sys.argv[0], *(argv if argv is not None else sys.argv[1:])],
              "subjects": [str(folder) for folder in folders], "fit_options": fit_options,
              "cpus_per_fit": cpus_per_fit, "rows": rows}
    path = write_json_atomic(output / RESULT_NAME, record)
    print(f"written: {path}")
    return 0 if all(row["status"] == 0 for row in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
