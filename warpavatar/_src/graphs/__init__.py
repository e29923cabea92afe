"""CUDA graphs: device work recorded once and relaunched without the host's cost of queueing it again (internal).

* :mod:`~warpavatar._src.graphs.capture`: the generic helpers. Torch and Warp work captured together into one
  ``torch.cuda.CUDAGraph`` (:func:`capture_cuda_graph`), the ``--cuda-graph auto|on|off`` setting as a yes/no
  for a device (:func:`resolve_cuda_graph`) and a capture that falls back to eager work under ``auto``
  (:func:`capture_or_fall_back`: playback, the cloth frame, the training step);
* :mod:`~warpavatar._src.graphs.address_graphs`: the rasterizer's default replays, graphs keyed by the addresses
  and sizes of the buffers a call touches and its launches' scalars (:class:`AddressKeyedGraphs`); they hold no
  buffer of their own;
* :mod:`~warpavatar._src.graphs.splat_replay`: the rasterizer's opt-in replays, graphs that own their input and
  output buffers (:class:`ReplayCache`), copied in and out on every call;
* :mod:`~warpavatar._src.graphs.status_mailbox`: a few int32 values the device copies into pinned host memory
  (also from inside a graph) and the host polls (:class:`StatusMailbox`), so reading a pass's pair count does not
  wait for the whole stream;
* :mod:`~warpavatar._src.graphs.step_graph`: a training step captured once and replayed while its key holds
  (:class:`StepGraph`); the trainer (``warpavatar/fit/trainer.py``) builds the key and runs the step through it.

Nothing is imported here: each module is imported by its own path.
"""

__all__ = ["address_graphs", "capture", "splat_replay", "status_mailbox", "step_graph"]
