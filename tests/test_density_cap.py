"""``--max-gaussians`` is a hard cap: a densification round never clones and splits past it, an initialization
with more Gaussians keeps a subset, and a round below the cap (or a fit that never reaches it) is unchanged."""

import pytest
import torch

from warpavatar import data
from warpavatar.fit import Trainer, preset
from warpavatar.fit.density import DensityControl, strongest
from warpavatar.model import GaussianModel


def test_strongest_keeps_the_largest_gradients_above_the_threshold():
    grad = torch.tensor([0.5, 3.0, 0.25, 2.0, 2.0, 9.0])
    assert strongest(grad, threshold=1.0, count=4) is grad  # four pass: nothing to drop
    assert strongest(grad, threshold=1.0, count=10) is grad
    kept = strongest(grad, threshold=1.0, count=2)
    assert kept.tolist() == [0.5, 3.0, 0.25, 0.0, 0.0, 9.0]  # below the threshold stays as it was
    tie = strongest(grad, threshold=1.0, count=3)
    assert tie.tolist() == [0.5, 3.0, 0.25, 2.0, 0.0, 9.0]  # of two equal values the lower index is kept
    assert (strongest(grad, threshold=1.0, count=0) >= 1.0).sum() == 0


def _round(count: int, *, cap: int, budget: float = 0.0, threshold: float = 1e-3):
    """One densification round of ``count`` Gaussians that all pass the threshold (half small: cloned, half
    large: split); the count after it."""
    generator = torch.Generator().manual_seed(0)
    means = torch.randn(count, 3, generator=generator)
    scales = torch.where(torch.arange(count)[:, None] % 2 == 0, 0.001, 0.05).expand(count, 3).clone()
    gaussians = GaussianModel(means, torch.rand(count, 3, generator=generator), scales, sh_degree=0, opacity=0.5)
    config = preset("quick", max_gaussians=cap, densify_slowdown=budget / cap, densify_grad_threshold=threshold,
                    densify_from=0, densify_every=1, densify_until=10, prune_max_scale=10.0)
    density = DensityControl(config, extent=1.0, generator=generator)
    density.reset(count, "cpu")
    density.grad_accum += torch.linspace(1.0, 2.0, count)[:, None]
    density.visible_count += 1.0
    renumbered = []
    extension = type("Recorder", (), {"before_densify": lambda self, visible: None,
                                      "on_gaussians_renumbered": lambda self, source: renumbered.append(source)})()
    density.after_step(1, gaussians, [extension])
    assert renumbered[0].shape[0] == gaussians.count
    return gaussians.count


def test_a_round_never_passes_the_cap():
    assert _round(100, cap=100_000) == 200  # below the cap: every Gaussian is cloned or split (+1 each)
    assert _round(100, cap=130) == 130  # at the cap: only the 30 largest gradients
    assert _round(100, cap=100) == 100 and _round(100, cap=60) == 100  # nothing added (more than the cap: kept)
    # past the soft budget (ToMiE A.4) the threshold rises, here to 0.5 * (2 + 20 / (80 / 6)) = 1.75, which the
    # gradients sqrt(2) * (1 + i / 99) pass from i = 24 on; from 1.5 times the budget no round densifies
    assert _round(100, cap=100_000, budget=80, threshold=0.5) == 100 + 76
    assert _round(100, cap=100_000, budget=60, threshold=1e-3) == 100
    assert _round(100, cap=150, budget=80, threshold=0.5) == 150  # both: the cap wins


@pytest.fixture(scope="module")
def video():
    return data.load_video_folder(data.demo_subject_path() / "train", max_frames=6, scale=0.25)


def _tiny(**overrides):
    values = dict(iterations=40, init_points_per_bone=10, init_carve_candidates=4000, init_carve_points=300,
                  sh_degree=0, grid_cells=12, grid_min_cells=4, field_hidden=16, field_layers=1, field_warmup_steps=4,
                  gaussian_only_steps=20, densify_from=5, densify_every=5, densify_until=35,
                  densify_grad_threshold=1e-7, checkpoint_every=1000, log_every=10, preview_frames=0,
                  densify_slowdown=0.0, refine_poses="off")
    return preset("quick", **{**values, **overrides})


def _counts(trainer) -> list[int]:
    """The Gaussian count at the start and after every step of ``trainer``'s fit."""
    counts = [trainer.gaussians.count]
    after_step = trainer.density.after_step

    def recording(step, gaussians, extensions):
        after_step(step, gaussians, extensions)
        counts.append(gaussians.count)

    trainer.density.after_step = recording
    trainer.fit(progress=False)
    return counts


def test_a_tiny_fit_with_a_small_cap_never_exceeds_it(video, tmp_path):
    free = _counts(Trainer(video, _tiny(), tmp_path / "free"))
    start = free[0]
    assert max(free) > start + 300  # with a threshold this low every round clones and splits
    cap = start + 150
    capped = _counts(Trainer(video, _tiny(max_gaussians=cap), tmp_path / "capped"))
    assert capped[0] == start and max(capped) == cap  # reached, never passed
    first_past = next(index for index, count in enumerate(free) if count > cap)
    assert capped[:first_past] == free[:first_past]  # the same fit until the cap binds


def test_an_initialization_larger_than_the_cap_keeps_a_subset(video, tmp_path):
    start = Trainer(video, _tiny(iterations=1), tmp_path / "all").gaussians.count
    trainer = Trainer(video, _tiny(max_gaussians=start // 2), tmp_path / "half")
    assert trainer.gaussians.count == start // 2
    counts = _counts(trainer)
    assert max(counts) == start // 2
