"""Fitting many subjects: one Ray task per subject (``warpavatar-fit-many``, ``docs/cluster.md``).

* :mod:`~warpavatar.batch.subjects`: the subjects of a batch (folders or list files), their names, their output
  folders and the done marker that lets a re-run skip them;
* :mod:`~warpavatar.batch.job`: one subject's fit (resuming from its checkpoint) and evaluation, the body of a
  task; it imports no Ray, so it runs and is tested without a cluster;
* :mod:`~warpavatar.batch.runner`: the Ray side: resources, retries, progress lines and the overall bar;
* :mod:`~warpavatar.batch.report`: the summary table, written as JSON and CSV in the output root.

Ray is an optional dependency (``pip install -e ".[cluster]"``); only :mod:`~warpavatar.batch.runner` imports it,
and only when a batch runs.
"""

from warpavatar.batch.job import INPUT_ERRORS, fit_subject
from warpavatar.batch.report import SUMMARY_NAME, summary_lines, write_summary
from warpavatar.batch.runner import RAY_INSTALL_HINT, run_batch
from warpavatar.batch.subjects import DONE_NAME, BatchSubject, finished_result, read_subjects

__all__ = ["BatchSubject", "read_subjects", "finished_result", "DONE_NAME", "fit_subject", "INPUT_ERRORS",
           "run_batch", "RAY_INSTALL_HINT", "summary_lines", "write_summary", "SUMMARY_NAME"]
