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

#: the metrics of each held-out folder that the CSV has a column for (``<folder> <metric>``)
_METRICS = ("psnr_masked", "ssim_masked", "psnr", "ssim", "lpips")


def _mean_masked_psnr(result: dict, kind: str) -> float | None:
    values = [metrics["psnr_masked"] for label, metrics in result.get("eval", {}).items()
              if label.startswith(kind + "/") and metrics.get("psnr_masked") is not None]
    return sum(values) / len(values) if values else None


def _minutes(seconds) -> str:
    return "" if seconds is None else f"{seconds / 60:.1f}"


def one_line_result(result: dict) -> str:
    """The progress line of a subject whose task ended, done (time, Gaussians, held-out masked PSNR) or failed
    (its error), or that an earlier run finished (skipped)."""
    if result["status"] == "failed":
        return f"{result['subject']}: failed: {result['error']}"
    if result["status"] == "skipped":
        return f"{result['subject']}: skipped, finished by an earlier run (--force fits it again)"
    held_out = ", ".join(f"{label} {metrics['psnr_masked']:.2f} dB" for label, metrics in result["eval"].items()
                         if metrics.get("psnr_masked") is not None)
    retried = f" after {result['attempts']} attempts" if result.get("attempts", 1) > 1 else ""
    return (f"{result['subject']}: done in {_minutes(result['wall_seconds'])} min{retried}, "
            f"{result['gaussians']} Gaussians" + (f"; masked PSNR {held_out}" if held_out else ""))


def summary_lines(results: list[dict]) -> list[str]:
    """The summary table: subject, status, attempts, minutes (the fit of the last attempt), Gaussians, mean
    masked PSNR on novel views and on novel poses (when evaluated), and the error of a failed subject."""
    header = ("subject", "status", "attempts", "fit min", "Gaussians", "novel view dB", "novel pose dB", "error")
    rows = []
    for result in results:
        view, pose = (_mean_masked_psnr(result, kind) for kind in ("novel_view", "novel_pose"))
        rows.append((result["subject"], result["status"], str(result.get("attempts", "")),
                     _minutes(result.get("fit_seconds")), str(result.get("gaussians") or ""),
                     "" if view is None else f"{view:.2f}", "" if pose is None else f"{pose:.2f}",
                     result.get("error") or ""))
    widths = [max(len(row[column]) for row in (header, *rows)) for column in range(len(header))]
    lines = ["  ".join(cell.ljust(width) for cell, width in zip(row, widths)).rstrip() for row in (header, *rows)]
    lines.insert(1, "  ".join("-" * width for width in widths))
    return lines


def _csv_text(results: list[dict]) -> str:
    labels = list(dict.fromkeys(label for result in results for label in result.get("eval", {})))
    columns = ["subject", "status", "attempts", "wall_seconds", "fit_seconds", "resume_step", "steps", "gaussians",
               "device", "preset", "output", "error"]
    metric_columns = [(label, metric) for label in labels for metric in _METRICS
                      if any(result.get("eval", {}).get(label, {}).get(metric) is not None for result in results)]
    text = io.StringIO()
    writer = csv.writer(text)
    writer.writerow(columns + [f"{label} {metric}" for label, metric in metric_columns])
    for result in results:
        values = [result.get(column) for column in columns]
        values += [result.get("eval", {}).get(label, {}).get(metric) for label, metric in metric_columns]
        writer.writerow(["" if value is None or (isinstance(value, float) and math.isnan(value)) else value
                         for value in values])
    return text.getvalue()


def write_summary(out_root: str | os.PathLike, results: list[dict]) -> tuple[Path, Path]:
    """Write the results as ``out_root/fit-many-summary.json`` (everything, per subject) and ``.csv`` (one row
    per subject, one column per held-out folder and metric), each through a temporary file and a rename."""
    from warpavatar.evaluate import write_json_atomic

    out_root = Path(out_root)
    json_path = write_json_atomic(out_root / f"{SUMMARY_NAME}.json", {"subjects": results})
    csv_path = out_root / f"{SUMMARY_NAME}.csv"
    tmp = csv_path.with_name(csv_path.name + ".tmp")
    tmp.write_text(_csv_text(results), encoding="utf-8")
    os.replace(tmp, csv_path)
    return json_path, csv_path
