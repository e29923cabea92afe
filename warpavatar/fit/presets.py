"""Named configurations: flat values (core fields, extension switches and options) over the defaults.

A preset is the core's values (:data:`CORE_PRESETS`) plus what each registered extension declares for it
(:attr:`~warpavatar.extensions.Extension.presets`: its switch and its options, e.g. a shorter schedule in
``quick``). A preset named in :data:`PRESET_BASES` starts from another preset's values (core and extensions)
and changes some of them.
"""

from __future__ import annotations

from warpavatar.extensions import registered
from warpavatar.fit.config import FitConfig

__all__ = ["CORE_PRESETS", "PRESET_BASES", "preset_names", "preset_values", "preset"]

CORE_PRESETS: dict[str, dict] = {
    # Quality preset, for a GPU.
    "default": {},
    # Small and fast: CPU fits in minutes, and the test suite.
    "quick": dict(
        iterations=2000,
        image_scale=0.5,
        init_points_per_bone=150,
        init_carve_candidates=60000,
        init_carve_points=6000,
        sh_degree=1,
        sh_increase_every=800,
        grid_cells=32,
        grid_min_cells=8,
        field_hidden=64,
        field_layers=3,
        field_warmup_steps=300,
        gaussian_only_steps=600,
        densify_from=200,
        densify_until=1400,
        densify_every=100,
        densify_slowdown=0.5,
        max_gaussians=20000,
        opacity_reset_every=0,
        checkpoint_every=500,
    ),
    # The built-in demo (warpavatar-fit --demo, README's first command): ``quick`` shortened to fit in about
    # 3 minutes on 2 CPU cores with the same held-out quality (BENCHMARKS.md, issue 18): 1200 steps, the
    # stages and densification window scaled with them, and half the Gaussians (the Warp compositing kernels,
    # single-threaded on the CPU, cost in proportion to them): densification slows past 4000 (quick's slowdown,
    # half the cap) and ends near 6.5k, below the cap.
    "demo": dict(
        iterations=1200,
        init_points_per_bone=60,
        init_carve_points=3000,
        sh_increase_every=400,
        field_warmup_steps=200,
        gaussian_only_steps=400,
        densify_from=150,
        densify_until=850,
        densify_every=70,
        max_gaussians=8000,
    ),
}

PRESET_BASES: dict[str, str] = {"demo": "quick"}
"""Presets that start from another preset's values (its core values and each extension's) and override some."""


def preset_names() -> list[str]:
    return sorted(CORE_PRESETS)


def preset_values(name: str) -> dict:
    """The flat values of preset ``name``: the core's, then each registered extension's.

    Raises:
        ValueError: an unknown preset, or two extensions that give one shared option different values.
    """
    if name not in CORE_PRESETS:
        raise ValueError(f"unknown preset {name!r}; choose one of {preset_names()}")
    base = preset_values(PRESET_BASES[name]) if name in PRESET_BASES else {}
    values = dict(CORE_PRESETS[name])
    for extension in registered():
        for key, value in extension.presets.get(name, {}).items():
            if key in values and values[key] != value:
                raise ValueError(f"preset {name!r}: {extension.__name__} sets {key}={value!r}, another part "
                                 f"{values[key]!r}")
            values[key] = value
    return {**base, **values}


def preset(name: str = "default", **overrides) -> FitConfig:
    """The named preset (``"default"``, ``"quick"`` or ``"demo"``) with some flat values overridden (core fields,
    extension switches such as ``dynamics=True``, extension options such as ``dynamics_hidden=32``)."""
    return FitConfig.from_flat({**preset_values(name), **overrides})
