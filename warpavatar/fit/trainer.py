"""Fitting an avatar to a video folder (TAGA's forward path): the training loop.

Stages (TAGA appendix C): (1) warm-up: the skinning field alone distils a rigid bone-distance prior; (2)
Gaussian-only: the Gaussians train under that frozen field; (3) joint: the field trains too, with the bone
regularization (:class:`~warpavatar.fit.skinning_field_stage.SkinningStage`). Adaptive density control runs with a
Gaussian budget (:class:`~warpavatar.fit.density.DensityControl`). Every optional part of the avatar is an
extension (:mod:`warpavatar.extensions`) whose hooks the loop calls in the registry's order: the loss is the
sum of ``weight * value`` over the terms that the core and each extension return, logged by name.
"""

from __future__ import annotations

import json
import math
import os
import time
from pathlib import Path

import torch
import tqdm

from warpavatar._src.graphs.step_graph import StepGraph
from warpavatar._src.precision import matmul_precision, mlp_precision
from warpavatar.extensions import FitContext, LossTerm, StepContext, get_extension
from warpavatar.fit.checkpoint import CHECKPOINT_NAME, check_resume, read_checkpoint, save_checkpoint, training_record
from warpavatar.fit.config import FitConfig
from warpavatar.fit.density import DensityControl
from warpavatar.fit.training_frames import TrainingFrames
from warpavatar.fit.init import initial_gaussians
from warpavatar.fit.outputs import TRAINING_MOTION_NAME, write_canonical_ply, write_previews, write_training_motion
from warpavatar.fit.skinning_field_stage import SkinningStage
from warpavatar.io.output_files import append_text, write_text_atomic
from warpavatar.metrics import image_loss_terms, psnr
from warpavatar.model import Avatar, GaussianModel, VoxelSkinningField
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
        self.log_path = self.output_dir / "train_log.jsonl"
        torch.manual_seed(config.seed)
        self.generator = torch.Generator().manual_seed(config.seed)
        self.frames = TrainingFrames(video, max_frames=config.max_train_frames, target=config.target,
                                     device=self.device)
        skeleton = video.skeleton
        positions, colours, bbox_min, bbox_max = initial_gaussians(skeleton, video, config, generator=self.generator,
                                                                   device=self.device)
        self.extent = float((bbox_max - bbox_min).norm()) * 0.5
        gaussians = GaussianModel(positions, colours, torch.full_like(positions, 0.01 * self.extent),
                                  sh_degree=config.sh_degree)
        field = VoxelSkinningField(bbox_min, bbox_max, skeleton.joint_count, cells=config.grid_cells,
                                   min_cells=config.grid_min_cells, hidden=config.field_hidden,
                                   layers=config.field_layers, frequencies=config.field_frequencies).to(self.device)
        self.avatar = Avatar(skeleton, gaussians, field)
        self.avatar.matmul_precision = config.matmul_precision
        if config.shading == "world":
            self.avatar.shading_origin = self.frames.camera_centre()
        self.skinning = SkinningStage(field, skeleton, config, extent=self.extent)
        self.density = DensityControl(config, extent=self.extent, generator=self.generator)
        self.density.reset(gaussians.count, self.device)
        context = FitContext(avatar=self.avatar, frames=self.frames, config=config, extent=self.extent,
                             skinning=self.skinning, density=self.density, log=self._log)
        #: the enabled extensions, in the registry's order (the order their hooks run)
        self.extensions = [get_extension(name)(options, context) for name, options in config.extensions.items()]
        for extension in self.extensions:
            extension.attach()
        self._make_gaussian_optimizer()
        self.step = 0
        self.frame_order: list[int] = []
        self._stop_requested = False
        #: the steady step captured and replayed as a CUDA graph (``cuda_graph``: auto, on, off)
        self.step_graph = StepGraph(self.device, cuda_graph)
        #: the rasterizer's sort capacity in (Gaussian, tile) pairs (``value`` None: the next step counts them)
        self.capacity = IntersectionCapacity(self.device)

    @property
    def gaussians(self) -> GaussianModel:
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

    def _make_gaussian_optimizer(self) -> None:
        config = self.config
        self.gaussians.make_optimizer(lr_position=config.lr_position * self.extent, lr_scale=config.lr_scale,
                                      lr_rotation=config.lr_rotation, lr_opacity=config.lr_opacity,
                                      lr_color=config.lr_color)

    def _next_frame(self) -> int:
        if not self.frame_order:
            self.frame_order = torch.randperm(self.frames.count, generator=self.generator).tolist()
        return self.frame_order.pop()

    def _position_lr(self, step: int) -> float:
        config = self.config
        fraction = min(1.0, step / max(1, config.iterations))
        start, end = config.lr_position * self.extent, config.lr_position_final * self.extent
        return math.exp(math.log(start) * (1 - fraction) + math.log(end) * fraction)

    def _core_losses(self, step: StepContext) -> dict[str, LossTerm]:
        """The photometric loss (L1 and D-SSIM), the mask and scale terms, and the skinning field's."""
        config = self.config
        image_terms = image_loss_terms(step.image, step.target, lambda_ssim=config.lambda_ssim, alpha=step.alpha,
                                       mask=step.mask, lambda_mask=config.lambda_mask)
        terms = {name: LossTerm(*term) for name, term in image_terms.items()}
        if config.lambda_scale > 0:
            terms["scale"] = LossTerm(config.lambda_scale,
                                      torch.relu(self.gaussians.scales - 0.05 * self.extent).mean())
        terms.update(self.skinning.losses(step, self.avatar.skinning_groups()))
        return terms

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
        terms = self._core_losses(step)
        for extension in self.extensions:
            for name, term in extension.losses(step).items():
                if name in terms:
                    raise ValueError(f"extension {extension.name!r} returns a loss term {name!r} another part has")
                terms[name] = term
        loss = sum(term.weight * term.value for term in terms.values())
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
        terms = {name: LossTerm(term.weight, term.value.detach()) for name, term in terms.items()}
        terms["loss"] = LossTerm(1.0, loss.detach())
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
            self._log({"step": self.step, "note": f"intersection capacity {exceeded} exceeded ({overflow} pairs): "
                       f"grown to {self.capacity.value}"})

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
        self.gaussians.set_position_lr(self._position_lr(number))
        inputs = {extension.name: value for extension in self.extensions
                  if (value := extension.frame_input(step)) is not None}
        degree = min(config.sh_degree, number // max(1, config.sh_increase_every))
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
            self._log({"step": number, "note": "CUDA graph capture failed, the fit goes on eagerly"})
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

    def _log_record(self, step: StepContext, terms: dict[str, LossTerm]) -> dict:
        record = {name: float(term.value.detach()) for name, term in terms.items()}
        for extension in self.extensions:
            record.update(extension.log_values())
        record.update(psnr=psnr(step.image.detach(), step.target), gaussians=self.gaussians.count)
        return record

    # ------------------------------------------------------------------------------------------- checkpoints
    def checkpoint_state(self) -> dict:
        return {
            "step": self.step,
            "config": self.config.to_dict(),
            "gaussians": self.gaussians.state_for_checkpoint(),
            "gaussian_optimizer": self.gaussians.optimizer.state_dict(),
            "skinning": self.skinning.state_dict(),
            "density": self.density.state_dict(),
            "generator": self.generator.get_state(),
            "frame_order": list(self.frame_order),
            "extensions": {extension.name: extension.state_dict() for extension in self.extensions},
            "training": training_record(self.frames.video),
        }

    def save_checkpoint(self) -> Path:
        return save_checkpoint(self.output_dir / CHECKPOINT_NAME, self.checkpoint_state())

    def load_checkpoint(self, path: str | os.PathLike) -> None:
        state = read_checkpoint(path)
        check_resume(path, state, config=self.config, video=self.frames.video)  # same options, skeleton, folder
        self.avatar.gaussians = GaussianModel.from_checkpoint(state["gaussians"], device=self.device)
        self._make_gaussian_optimizer()
        self.gaussians.optimizer.load_state_dict(state["gaussian_optimizer"])
        # extensions first: one may give the field outputs (grown joints) that its saved state has
        for extension in self.extensions:
            extension.load_state_dict(state["extensions"][extension.name])
        self.skinning.load_state_dict(state["skinning"])
        self.density.load_state_dict(state["density"], device=self.device)
        self.generator.set_state(state["generator"])
        self.frame_order = list(state["frame_order"])
        self.step = int(state["step"])

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
            self.log_path.unlink(missing_ok=True)
            write_text_atomic(self.output_dir / "config.json", config.to_json())
            warm = self.skinning.warmup(config.field_warmup_steps)
            self._log({"stage": "warmup", "distillation_loss": warm, "gaussians": self.gaussians.count})
        start_time = time.time()
        end = config.iterations if stop_at is None else min(stop_at, config.iterations)
        bar = tqdm.tqdm(total=config.iterations, initial=self.step, disable=not progress, desc="fit", unit="step")
        while self.step < end and not self._stop_requested:
            step, terms = self.train_step()
            bar.update(1)
            if self.step % config.log_every == 0 or self.step == config.iterations:
                self.check_rasterizer()
                record = self._log_record(step, terms)  # the only host reads of a step, every log_every steps
                record.update(self.step_graph.log_values(), **self.skinning.log_values())
                self._log({**record, "step": self.step, "seconds": round(time.time() - start_time, 2)})
                bar.set_postfix(loss=f"{record['loss']:.4f}", psnr=f"{record['psnr']:.2f}", n=record["gaussians"])
            if self.step % config.checkpoint_every == 0 and self.step < config.iterations:
                self.save_checkpoint()
        bar.close()
        if self.step >= config.iterations:
            self.write_outputs()
        else:
            self.save_checkpoint()
        return self.avatar

    def _log(self, record: dict) -> None:
        append_text(self.log_path, json.dumps(record) + "\n")

    def summary_lines(self) -> list[str]:
        """What the extensions report about the finished fit (for the command line)."""
        return [line for extension in self.extensions for line in extension.summary_lines()]

    def write_outputs(self) -> None:
        """Avatar file, canonical .ply, the training motion, previews of a few training frames; the last checkpoint
        stays."""
        for extension in self.extensions:
            extension.finish()
        self.avatar.save(self.output_dir / "avatar.pt", config=self.config.to_dict())
        write_canonical_ply(self.gaussians, self.output_dir / "canonical.ply")
        write_training_motion(self.frames, self.output_dir / TRAINING_MOTION_NAME)
        for extension in self.extensions:
            extension.write_outputs(self.output_dir)
        self.save_checkpoint()
        write_previews(self.avatar, self.frames, self.output_dir / "previews", count=self.config.preview_frames)

