"""A training step's device work captured once as a CUDA graph and replayed while what it depends on holds.

The trainer says what a step depends on beyond its buffers' values (its *key*: shapes, schedules, the storage
of every tensor it updates). :meth:`StepGraph.replay` reruns the captured step when the key is the one it was
captured with; otherwise :meth:`StepGraph.run_then_capture` runs the step eagerly on the capture stream and
captures a second run of its work for the steps that follow.
"""

from __future__ import annotations

from typing import Any, Callable

import torch

from warpavatar._src.graphs.capture import capture_or_fall_back, resolve_cuda_graph

__all__ = ["StepGraph"]


class StepGraph:
    """The captured training step of a fit.

    Args:
        device: the training device.
        mode: ``--cuda-graph``: ``auto`` (capture on CUDA; a failed capture turns capturing off), ``on`` (a
            failed capture raises) or ``off``.

    Attributes:
        enabled: whether steps are captured (False off CUDA, with ``off``, or after a failed capture).
        replays: steps replayed so far.
        captures: graphs captured so far (one per change of the step's key, e.g. each densification).
    """

    def __init__(self, device, mode: str):
        self.device = torch.device(device)
        self.mode = mode
        self.enabled = resolve_cuda_graph(mode, self.device)
        self.replays = 0
        self.captures = 0
        self._stream = torch.cuda.Stream(device=self.device) if self.enabled else None
        self._captured: tuple | None = None  # (key, torch.cuda.CUDAGraph, its outputs)

    @staticmethod
    def optimizer_storage(optimizers) -> tuple:
        """What a captured step's optimizers update, for its key: each optimizer's identity and the storage of every
        parameter and state tensor (moments, step counts); a new one means capturing again."""
        return (tuple(id(optimizer) for optimizer in optimizers),
                tuple(tensor.data_ptr() for optimizer in optimizers for group in optimizer.param_groups
                      for parameter in group["params"]
                      for tensor in (parameter, *(value for value in optimizer.state.get(parameter, {}).values()
                                                  if isinstance(value, torch.Tensor)))))

    def log_values(self) -> dict[str, int]:
        """Captures and replays so far, for the fit's log (nothing while capturing is off)."""
        return {"graph_captures": self.captures, "graph_replays": self.replays} if self.enabled else {}

    def replay(self, key) -> Any | None:
        """Rerun the captured step and return its outputs (overwritten in place), or None when nothing was
        captured with this key."""
        if self._captured is None or self._captured[0] != key:
            return None
        self._captured[1].replay()
        self.replays += 1
        return self._captured[2]

    def run(self, key, work: Callable[[], Any], capture_work: Callable[[], Any], *, between: Callable[[], None],
            rekey: Callable[[], Any]) -> Any:
        """One step: replayed when a graph was captured under ``key``; otherwise ``work`` runs eagerly, and, when
        ``key`` is not None (the step may be captured), ``capture_work`` is then captured under ``rekey()`` for the
        steps that follow (:meth:`run_then_capture`). ``work`` and ``capture_work`` return the same structure.

        Returns:
            The step's outputs (a replay's are the captured tensors, overwritten in place).
        """
        if key is None:
            return self.run_eager(work)
        replayed = self.replay(key)
        if replayed is not None:
            return replayed
        return self.run_then_capture(work, capture_work, between=between, key=rekey)

    def run_eager(self, work: Callable[[], Any]) -> Any:
        """Run a step that is not captured: on the capture stream while capturing is on, so that the autograd
        nodes it creates (a parameter's AccumulateGrad node lives as long as any graph holds it) belong to the
        stream that later captures use; a node bound to another stream makes a capture synchronize with that
        stream, which invalidates it."""
        if not self.enabled:
            return work()
        current = torch.cuda.current_stream(self.device)
        self._stream.wait_stream(current)
        with torch.cuda.stream(self._stream):
            result = work()
        current.wait_stream(self._stream)
        return result

    def run_then_capture(self, work: Callable[[], Any], capture_work: Callable[[], Any], *,
                         between: Callable[[], None], key: Callable[[], Any]) -> Any:
        """Run ``work`` eagerly on the capture stream, call ``between``, then capture ``capture_work`` under the key
        that ``key()`` gives afterwards (the eager step may have made state, e.g. an optimizer's first moments).

        Returns:
            What ``work`` returned.
        """
        self._captured = None
        current = torch.cuda.current_stream(self.device)
        self._stream.wait_stream(current)
        with torch.cuda.stream(self._stream):
            result = work()
        current.wait_stream(self._stream)
        between()
        captured = capture_or_fall_back(capture_work, mode=self.mode, what="the fit", device=self.device, warmup=0,
                                        stream=self._stream)
        if captured is None:
            self.enabled = False
        else:
            self._captured = (key(), *captured)
            self.captures += 1
        return result
