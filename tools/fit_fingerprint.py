"""Fingerprints of tiny fits, to show that a change of the code changes no result.

    python tools/fit_fingerprint.py OUT.pt [--cases secondary dynamics ...] [--device cpu]
    python tools/fit_fingerprint.py OUT.pt --compare BEFORE.pt

Runs one tiny fit of the demo subject per combination of the optional parts (60 steps on 12 training frames,
densification every 10 steps: every stage and every extension hook runs) and saves each fit's final Gaussians,
skinning field and three renders. ``--compare`` prints, per case, the largest difference from another
fingerprint file (made by this tool with other code, e.g. in a ``git worktree`` of an earlier commit). On the
CPU a fit is deterministic, so a change that should change nothing shows zeros.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from tempfile import TemporaryDirectory

import torch

from warpavatar import data
from warpavatar.fit import Trainer, load_training_video, preset

BASE = dict(iterations=60, image_scale=0.5, max_train_frames=12, init_points_per_bone=30,
            init_carve_candidates=20000, init_carve_points=1500, sh_degree=1, sh_increase_every=20, grid_cells=16,
            grid_min_cells=6, field_hidden=32, field_layers=2, field_warmup_steps=40, gaussian_only_steps=25,
            densify_from=10, densify_until=50, densify_every=10, max_gaussians=12000, checkpoint_every=1000,
            log_every=10, preview_frames=1, pose_correction=True, pose_correction_hidden=16, secondary_from=25)
CASES = {
    "secondary": dict(secondary_motion=True),
    "light_backward": dict(secondary_motion=True, lighting=True, backward_mapping=True, backward_from=30,
                           backward_every=10, backward_until=60),
    "dynamics": dict(dynamics=True, dynamics_hidden=16, dynamics_window=3, dynamics_refresh_every=10),
    "grow": dict(secondary_motion=True, grow_joints=True, grow_at=30, grow_threshold=0.5, grow_max_joints=2,
                 grow_kernel_frames=6),
    "grow_history": dict(grow_joints=True, grow_at=40, grow_criterion="history", grow_threshold=0.5,
                         grow_max_joints=1, grow_kernel_frames=6),
    "plain": dict(pose_correction=False, shading="view"),
}


def fingerprint(name: str, video, *, device: str) -> dict:
    """Fit case ``name`` and return its final parameters and three renders."""
    with TemporaryDirectory() as folder:
        trainer = Trainer(video, preset("quick", **{**BASE, **CASES[name]}), folder, device=device)
        trainer.fit(progress=False)
    avatar, frames = trainer.avatar, trainer.frames
    gaussians = {key: getattr(avatar.gaussians, key).detach().cpu().clone()
                 for key in ("means", "log_scales", "quats", "opacity_logits", "sh_dc", "sh_rest")}
    with torch.no_grad():
        renders = torch.stack([avatar.render(frames.cameras[i], frames.bone_transforms[i])[0].cpu()
                               for i in (0, 5, 11)])
    field = {key: value.detach().cpu().clone() for key, value in avatar.field.state_dict().items()}
    return {"gaussians": gaussians, "field": field, "renders": renders}


def largest_difference(a: dict, b: dict) -> str:
    """The largest absolute difference of parameters and renders, or where the two differ in shape."""
    worst = 0.0
    for group in ("gaussians", "field"):
        for key, value in a[group].items():
            other = b[group].get(key)
            if other is None or other.shape != value.shape:
                shape = None if other is None else list(other.shape)
                return f"{group}.{key} differs: shape {list(value.shape)} against {shape}"
            worst = max(worst, float((value.float() - other.float()).abs().max()) if value.numel() else 0.0)
    render = float((a["renders"] - b["renders"]).abs().max())
    return f"parameters {worst:.3g}, renders {render:.3g}"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("output", type=Path, help="the fingerprint file to write (.pt)")
    parser.add_argument("--cases", nargs="+", choices=sorted(CASES), default=list(CASES),
                        help="which combinations of optional parts to fit (default: all)")
    parser.add_argument("--compare", type=Path, default=None, help="a fingerprint file to compare with")
    parser.add_argument("--device", default="cpu", help="torch device (default: cpu, where fits are deterministic)")
    args = parser.parse_args(argv)
    video = load_training_video(data.demo_subject_path() / "train", preset("quick", **BASE))
    result = {name: fingerprint(name, video, device=args.device) for name in args.cases}
    torch.save(result, args.output)
    if args.compare is not None:
        before = torch.load(args.compare, weights_only=True)
        for name, values in result.items():
            print(f"{name}: " + (largest_difference(before[name], values) if name in before else "not in the other"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
