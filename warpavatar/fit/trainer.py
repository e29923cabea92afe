"""Fitting an avatar to a video folder (TAGA's forward path): the training loop.

Stages (TAGA appendix C): (1) warm-up: the skinning field alone distils a rigid bone-distance prior; (2)
Gaussian-only: the Gaussians train under that frozen field; (3) joint: the field trains too, with the bone
regularization (:class:`~warpavatar.fit.skinning_field_stage.SkinningStage`). Adaptive density control runs with a
Gaussian budget (:class:`~warpavatar.fit.density.DensityControl`). Every optional part of the avatar is an
extension (:mod:`warpavatar.extensions`) whose hooks the loop calls in the registry's order: the loss is the
sum of ``weight * value`` over the terms that the core and each extension return, logged by name.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import torch
import tqdm

from warpavatar._src.graphs.step_graph import StepGraph
from warpavatar._src.precision import matmul_precision, mlp_precision
from warpavatar.extensions import FitContext, LossTerm, StepContext, get_extension
from warpavatar.fit.checkpoint import (CHECKPOINT_NAME, check_resume, read_checkpoint, restore_trainer_state,
                                       save_checkpoint, trainer_state)
from warpavatar.fit.config import FitConfig
from warpavatar.fit.density import DensityControl
from warpavatar.fit.training_frames import TrainingFrames
from warpavatar.fit.init import initial_avatar
from warpavatar.fit.loss_terms import add_extension_loss_terms, core_loss_terms, detached_loss_terms, weighted_loss
from warpavatar.fit.outputs import write_fitted_avatar, write_previews
from warpavatar.fit.schedule import active_sh_degree, make_gaussian_optimizer, position_learning_rate
from warpavatar.fit.skinning_field_stage import SkinningStage
from warpavatar.fit.training_log import TRAINING_LOG_NAME, TrainingLog, step_log_record
from warpavatar.io.output_files import write_text_atomic
from warpavatar.model import Avatar, GaussianModel
from warpavatar.model.capacity import IntersectionCapacity

__all__ = ["Trainer"]


class Trainer:
    """Fits an :class:`~warpavatar.model.avatar.Avatar` to one video folder.

    Args:
        video: the training :class:`~warpavatar.data.VideoFolder` (:func:`~warpavatar.fit.load_training_video`).
        config: the fit configuration.
        output_dir: where checkpoints, the avatar file, the log and previews go.
        device: torch device to train on.
        cuda_graph: ``auto`` (on CUDA: capture the steady training step as a CUDA graph and replay it; should a
            capture fail, the fit logs it and goes on eagerly), ``on`` (the same, CUDA required, a failed capture
            raises) or ``off`` (every step eager). The results are the same either way, up to the rounding of
            atomic additions, which differs from run to run anyway.
    """

    def __init__(self, video, config: FitConfig, output_dir: str | os.PathLike, *, device="cpu",
                 cuda_graph: str = "auto"):
        self.config = config
        self.output_dir = Path(output_dir)
        self.device = torch.device(device)
        self.output_dir.mkdir(parents=True, exist_ok=True)
        self.training_log = TrainingLog(self.output_dir / TRAINING_LOG_NAME)
        self.log_path = self.training_log.path
        torch.manual_seed(config.seed)
        self.generator = torch.Generator().manual_seed(config.seed)
        self.frames = TrainingFrames(video, max_frames=config.max_train_frames, target=config.target,
                                     device=self.device)
        self.avatar, self.extent = initial_avatar(video, self.frames, config, generator=self.generator,
                                                  device=self.device)
        self.skinning = SkinningStage(self.avatar.field, video.skeleton, config, extent=self.extent)
        self.density = DensityControl(config, extent=self.extent, generator=self.generator)
        self.density.reset(self.gaussians.count, self.device)
        context = FitContext(avatar=self.avatar, frames=self.frames, config=config, extent=self.extent,
                             skinning=self.skinning, density=self.density, log=self.training_log.write)
        #: the enabled extensions, in the registry's order (the order their hooks run)
        self.extensions = [get_extension(name)(options, context) for name, options in config.extensions.items()]
        for extension in self.extensions:
            extension.attach()
        make_gaussian_optimizer(self.gaussians, config, extent=self.extent)
        self.step = 0
        self.frame_order: list[int] = []
        self._stop_requested = False
        #: the steady step captured and replayed as a CUDA graph (``cuda_graph``: auto, on, off)
        self.step_graph = StepGraph(self.device, cuda_graph)
        #: the rasterizer's sort capacity in (Gaussian, tile) pairs (``value`` None: the next step counts them)
        self.capacity = IntersectionCapacity(self.device)

    @property
    def gaussians(self) -> GaussianModel:
        """The avatar's canonical Gaussians (a new model after each densification round or a resume)."""
        return self.avatar.gaussians

    @property
    def use_cuda_graph(self) -> bool:
        """Whether steady steps are captured and replayed as a CUDA graph."""
        return self.step_graph.enabled

    @property
    def graph_replays(self) -> int:
        """Steps replayed from a captured CUDA graph so far (this session)."""
        return self.step_graph.replays

    @property
    def intersection_capacity(self) -> int | None:
        """The rasterizer's sort capacity the next step uses (None: exact buffers, counting the pairs)."""
        return self.capacity.value

    def extension(self, name: str):
        """The enabled extension called ``name``, or None."""
        return next((extension for extension in self.extensions if extension.name == name), None)

    def _next_frame(self) -> int:
        if not self.frame_order:
            self.frame_order = torch.randperm(self.frames.count, generator=self.generator).tolist()
        return self.frame_order.pop()

    # ------------------------------------------------------------------------------------------------ a step
    def _step_work(self, step: StepContext, buffers, degree: int, inputs: dict, optimizers: list):
        """The device work of a step, from the frame's buffers to the optimizers' update: no host reads, so it
        runs eagerly or is captured as a CUDA graph. Returns (image, alpha, loss terms incl. ``loss``)."""
        frames = self.frames
        step.frame = buffers.index
        inputs = {**inputs, **{extension.name: value for extension in self.extensions
                               if (value := extension.step_input(step)) is not None}}
        step.target, step.mask = frames.target_of(buffers.image, buffers.mask)
        grad_out = torch.zeros(self.gaussians.count, 2, device=self.device)
        step.posed = self.avatar.pose(buffers.bones, grid=step.grid, inputs=inputs, sh_degree=degree)
        step.image, step.alpha, step.depth, info = self.avatar.rasterize(
            step.posed, buffers.camera, background=frames.background, densify_grad_out=grad_out, return_info=True,
            intersection_capacity=self.capacity.value)
        terms = core_loss_terms(step, config=self.config, gaussians=self.gaussians, extent=self.extent)
        terms.update(self.skinning.losses(step, self.avatar.skinning_groups()))
        add_extension_loss_terms(terms, self.extensions, step)
        loss = weighted_loss(terms)
        for optimizer in optimizers:
            optimizer.zero_grad(set_to_none=True)
        with matmul_precision(self.config.matmul_precision, self.device):
            loss.backward()
        for extension in self.extensions:
            extension.after_backward(step)
        for optimizer in optimizers:
            optimizer.step()
        for extension in self.extensions:
            extension.after_step(step)
        self.density.accumulate(grad_out, info["radii"], buffers.camera)
        self.capacity.record(info["status"])  # on the device until the next check
        # Nothing the step returns keeps its autograd graph alive: a graph that outlives the step keeps the
        # parameters' AccumulateGrad nodes, bound to the stream they were made on, and a later step captured on
        # another stream would then synchronize with that one, which invalidates the capture.
        self.skinning.release_graph()
        terms = detached_loss_terms(terms, loss)
        step.posed = type(step.posed)({name: value.detach() if isinstance(value, torch.Tensor) else value
                                       for name, value in step.posed.items()})
        step.image, step.alpha, step.depth = step.image.detach(), step.alpha.detach(), step.depth.detach()
        return step.image, step.alpha, terms

    def _graph_key(self, step: StepContext, degree: int, buffers, optimizers: list) -> tuple:
        """What a captured step depends on beyond its buffers' values: shapes, schedules and the storage of every
        tensor it updates (a new parameter, moment or statistic means capturing again)."""
        return (degree, step.train_field, self.gaussians.count, self.capacity.value, id(buffers),
                StepGraph.optimizer_storage(optimizers), self.density.grad_accum.data_ptr(),
                self.density.visible_count.data_ptr(), self.skinning.graph_key(),
                tuple(extension.graph_key(step) for extension in self.extensions))

    def check_rasterizer(self) -> None:
        """Read the rasterizer's status (:meth:`IntersectionCapacity.check`: one host read, at
        log steps and after densification) and log a capacity that steps exceeded (they dropped pairs).

        Raises:
            ValueError: a step rasterized non-finite values.
        """
        exceeded = self.capacity.value
        overflow = self.capacity.check()
        if overflow is not None:
            self.training_log.write({"step": self.step, "note": f"intersection capacity {exceeded} exceeded "
                                     f"({overflow} pairs): grown to {self.capacity.value}"})

    def train_step(self) -> tuple[StepContext, dict[str, LossTerm]]:
        """One optimizer step on one training frame; returns the step and its loss terms (device tensors).

        The step's device work (:meth:`_step_work`) reads nothing from the device. On CUDA (``cuda_graph``) it is
        captured as a graph once shapes and parameters settle and replayed while they stay, unless an extension
        says the step cannot be (:meth:`~warpavatar.extensions.Extension.step_capturable`).
        The MLPs and the backward's GEMMs run in ``--matmul-precision`` (:mod:`warpavatar._src.precision`), eager
        or captured alike.
        """
        with mlp_precision(self.config.matmul_precision):
            return self._train_step()

    def _train_step(self) -> tuple[StepContext, dict[str, LossTerm]]:
        config = self.config
        number = self.step
        train_field = number >= config.gaussian_only_steps
        self.skinning.begin_step(number, self.gaussians.means, train_field=train_field)
        step = StepContext(step=number, index=self._next_frame(), train_field=train_field,
                           read_grid=lambda: self.skinning.grid(number, train_field=train_field))
        for extension in self.extensions:
            extension.begin_step(step)
        self.gaussians.set_position_lr(position_learning_rate(config, number, extent=self.extent))
        inputs = {extension.name: value for extension in self.extensions
                  if (value := extension.frame_input(step)) is not None}
        degree = active_sh_degree(config, number)
        buffers = self.frames.step_buffers(step.index)
        optimizers = [self.gaussians.optimizer, *self.skinning.optimizers(step)]
        for extension in self.extensions:
            optimizers += extension.optimizers(step)
        capturable = (self.step_graph.enabled and self.capacity.value is not None and not inputs
                      and all(extension.step_capturable(step) for extension in self.extensions))
        key = self._graph_key(step, degree, buffers, optimizers) if capturable else None

        def work(context: StepContext):
            image, alpha, terms = self._step_work(context, buffers, degree, inputs, optimizers)
            return image, alpha, terms, context.posed, context.target, context.mask

        # a capture runs the step's work a second time, in a context of its own (its outputs are the graph's)
        capture = StepContext(step=number, index=step.index, train_field=train_field, read_grid=step.read_grid)
        image, alpha, terms, step.posed, step.target, step.mask = self.step_graph.run(
            key, lambda: work(step), lambda: work(capture),
            between=self.skinning.forget_step,  # the graph evaluates the grid itself
            rekey=lambda: self._graph_key(step, degree, buffers, optimizers))
        if key is not None and not self.step_graph.enabled:
            self.training_log.write({"step": number, "note": "CUDA graph capture failed, the fit goes on eagerly"})
        step.image, step.alpha = image, alpha
        count = self.gaussians.count
        self.density.after_step(number, self.gaussians, self.extensions)
        if self.capacity.value is None:
            self.check_rasterizer()
        elif self.gaussians.count != count:  # new Gaussians: the next step counts their pairs with exact buffers
            self.check_rasterizer()
            self.capacity.value = None
        self.step += 1
        return step, terms

    # ------------------------------------------------------------------------------------------- checkpoints
    def checkpoint_state(self) -> dict:
        """What a checkpoint holds of this fit (:func:`~warpavatar.fit.checkpoint.trainer_state`)."""
        return trainer_state(self)

    def save_checkpoint(self) -> Path:
        """Write :meth:`checkpoint_state` to ``checkpoint.pt`` in the output folder (atomically); returns its path."""
        return save_checkpoint(self.output_dir / CHECKPOINT_NAME, self.checkpoint_state())

    def load_checkpoint(self, path: str | os.PathLike) -> None:
        """Continue from the checkpoint at ``path``.

        Raises:
            ValueError: one made with other options, skeleton or video folder (:func:`check_resume`), or unreadable.
        """
        state = read_checkpoint(path)
        check_resume(path, state, config=self.config, video=self.frames.video)  # same options, skeleton, folder
        restore_trainer_state(self, state)

    # ------------------------------------------------------------------------------------------------ run
    def request_stop(self) -> None:
        """Make :meth:`fit` stop after the step under way and write a checkpoint there (safe from a signal
        handler: it only sets a flag)."""
        self._stop_requested = True

    @property
    def stopped_early(self) -> bool:
        """Whether the last :meth:`fit` ended before the last step (a stop request or ``stop_at``)."""
        return self.step < self.config.iterations

    def fit(self, *, resume: bool = False, progress: bool = True, stop_at: int | None = None) -> Avatar:
        """Run (or continue) the fit and write the outputs.

        Args:
            resume: continue from ``checkpoint.pt`` in the output folder when it exists.
            progress: show a tqdm progress bar.
            stop_at: stop after this step (as an interruption would), without writing final outputs.
        """
        config = self.config
        checkpoint = self.output_dir / CHECKPOINT_NAME
        if resume and checkpoint.is_file():
            self.load_checkpoint(checkpoint)
        else:
            self.training_log.clear()
            write_text_atomic(self.output_dir / "config.json", config.to_json())
            warm = self.skinning.warmup(config.field_warmup_steps)
            self.training_log.write({"stage": "warmup", "distillation_loss": warm, "gaussians": self.gaussians.count})
        start_time = time.time()
        end = config.iterations if stop_at is None else min(stop_at, config.iterations)
        bar = tqdm.tqdm(total=config.iterations, initial=self.step, disable=not progress, desc="fit", unit="step")
        while self.step < end and not self._stop_requested:
            step, terms = self.train_step()
            bar.update(1)
            if self.step % config.log_every == 0 or self.step == config.iterations:
                self.check_rasterizer()
                # the only host reads of a step, every log_every steps
                record = step_log_record(step, terms, extensions=self.extensions, gaussian_count=self.gaussians.count,
                                         stages=(self.step_graph, self.skinning), step_number=self.step,
                                         seconds=time.time() - start_time)
                self.training_log.write(record)
                bar.set_postfix(loss=f"{record['loss']:.4f}", psnr=f"{record['psnr']:.2f}", n=record["gaussians"])
            if self.step % config.checkpoint_every == 0 and self.step < config.iterations:
                self.save_checkpoint()
        bar.close()
        if self.step >= config.iterations:
            self.write_outputs()
        else:
            self.save_checkpoint()
        return self.avatar

    def summary_lines(self) -> list[str]:
        """What the extensions report about the finished fit (for the command line)."""
        return [line for extension in self.extensions for line in extension.summary_lines()]

    def write_outputs(self) -> None:
        """Avatar file, canonical .ply, the training motion, previews of a few training frames; the last checkpoint
        stays."""
        write_fitted_avatar(self.avatar, self.frames, self.extensions, self.output_dir, config=self.config)
        self.save_checkpoint()
        write_previews(self.avatar, self.frames, self.output_dir / "previews", count=self.config.preview_frames)

