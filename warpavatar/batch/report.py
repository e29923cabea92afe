"""The batch's summary: one line per finished subject, the table at the end, and its JSON and CSV files."""

from __future__ import annotations

import csv
import io
import math
import os
from pathlib import Path

__all__ = ["SUMMARY_NAME", "one_line_result", "summary_lines", "write_summary"]

#: the summary files in the output root: ``<SUMMARY_NAME>.json`` and ``<SUMMARY_NAME>.csv``
SUMMARY_NAME = "fit-many-summary"

#: the metrics of each held-out folder that the CSV has a column for (``<folder> <metric>``), and the resolution
#: they were computed at
_METRICS = ("psnr_masked", "ssim_masked", "floater_share", "psnr", "ssim", "lpips", "resolution")


def _mean_masked_psnr(result: dict, kind: str) -> float | None:
    values = [metrics["psnr_masked"] for label, metrics in result.get("eval", {}).items()
              if label.startswith(kind + "/") and metrics.get("psnr_masked") is not None]
    return sum(values) / len(values) if values else None


def _minutes(seconds) -> str:
    return "" if seconds is None else f"{seconds / 60:.1f}"


def one_line_result(result: dict) -> str:
    """The progress line of a subject whose task ended, done (time, Gaussians, held-out masked PSNR), failed (its
    error) or interrupted (the step its checkpoint holds), or that an earlier run finished (skipped)."""
    if result["status"] == "failed":
        return f"{result['subject']}: failed: {result['error']}"
    if result["status"] == "skipped":
        return f"{result['subject']}: skipped, finished by an earlier run (--force fits it again)"
    if result["status"] == "interrupted":
        if result.get("steps") is None:
            return f"{result['subject']}: stopped before its training steps (an earlier checkpoint stays)"
        return f"{result['subject']}: stopped at step {result['steps']}, its checkpoint written"
    from warpavatar.evaluate import held_out_resolution

    masked = {label: metrics for label, metrics in result["eval"].items() if metrics.get("psnr_masked") is not None}
    held_out = ", ".join(f"{label} {metrics['psnr_masked']:.2f} dB" for label, metrics in masked.items())
    resolution = held_out_resolution(masked)  # the fit's training resolution
    if held_out and resolution:
        held_out += f" at {resolution}"
    retried = f" after {result['attempts']} attempts" if result.get("attempts", 1) > 1 else ""
    return (f"{result['subject']}: done in {_minutes(result['wall_seconds'])} min{retried}, "
            f"{result['gaussians']} Gaussians" + (f"; masked PSNR {held_out}" if held_out else ""))


def summary_lines(results: list[dict]) -> list[str]:
    """The summary table: subject, status, attempts, minutes (the fit of the last attempt), Gaussians, mean
    masked PSNR on novel views and on novel poses (when evaluated) and the resolution it was computed at, and
    the error of a failed subject."""
    from warpavatar.evaluate import held_out_resolution

    header = ("subject", "status", "attempts", "fit min", "Gaussians", "novel view dB", "novel pose dB", "at",
              "error")
    rows = []
    for result in results:
        view, pose = (_mean_masked_psnr(result, kind) for kind in ("novel_view", "novel_pose"))
        rows.append((result["subject"], result["status"], str(result.get("attempts", "")),
                     _minutes(result.get("fit_seconds")), str(result.get("gaussians") or ""),
                     "" if view is None else f"{view:.2f}", "" if pose is None else f"{pose:.2f}",
                     held_out_resolution(result.get("eval") or {}), result.get("error") or ""))
    widths = [max(len(row[column]) for row in (header, *rows)) for column in range(len(header))]
    lines = ["  ".join(cell.ljust(width) for cell, width in zip(row, widths)).rstrip() for row in (header, *rows)]
    lines.insert(1, "  ".join("-" * width for width in widths))
    return lines


def _csv_text(results: list[dict]) -> str:
    labels = list(dict.fromkeys(label for result in results for label in result.get("eval", {})))
    columns = ["subject", "status", "attempts", "wall_seconds", "fit_seconds", "resume_step", "steps", "gaussians",
               "device", "host", "gpu", "preset", "output", "error"]
    metric_columns = [(label, metric) for label in labels for metric in _METRICS
                      if any(result.get("eval", {}).get(label, {}).get(metric) is not None for result in results)]
    text = io.StringIO()
    writer = csv.writer(text)
    writer.writerow(columns + [f"{label} {metric}" for label, metric in metric_columns])
    for result in results:
        # the GPU by the UUID nvidia-smi -L prints
        values = [(result.get("gpu") or {}).get("uuid") if column == "gpu" else result.get(column)
                  for column in columns]
        values += [result.get("eval", {}).get(label, {}).get(metric) for label, metric in metric_columns]
        writer.writerow(["" if value is None or (isinstance(value, float) and math.isnan(value)) else value
                         for value in values])
    return text.getvalue()


def write_summary(out_root: str | os.PathLike, results: list[dict]) -> tuple[Path, Path]:
    """Write the results as ``out_root/fit-many-summary.json`` (everything, per subject) and ``.csv`` (one row
    per subject, one column per held-out folder and metric), each through a temporary file and a rename."""
    from warpavatar.io.output_files import write_json_atomic, write_text_atomic

    out_root = Path(out_root)
    json_path = write_json_atomic(out_root / f"{SUMMARY_NAME}.json", {"subjects": results})
    csv_path = write_text_atomic(out_root / f"{SUMMARY_NAME}.csv", _csv_text(results))
    return json_path, csv_path
