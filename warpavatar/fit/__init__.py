"""Fitting an avatar to a video folder: the configuration and its presets, the training loop and its core
stages (initialization, skinning field, density control, checkpoints)."""

from warpavatar.fit.checkpoint import CHECKPOINT_NAME
from warpavatar.fit.config import FitConfig
from warpavatar.fit.presets import preset, preset_names, preset_values
from warpavatar.fit.trainer import Trainer
from warpavatar.fit.training_frames import load_training_video

__all__ = ["FitConfig", "preset", "preset_names", "preset_values", "Trainer", "CHECKPOINT_NAME", "load_training_video"]
