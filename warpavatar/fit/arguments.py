"""The ``warpavatar-fit`` flags: one kebab-case flag per core field, extension switch and extension option,
grouped for ``--help`` (main options first, then the core's groups, then each extension's research knobs)."""

from __future__ import annotations

import argparse
import dataclasses
import math
from dataclasses import fields

from warpavatar.extensions import registered
from warpavatar.fit.config import CORE_GROUPS, RANGES, FitConfig, option_owners, range_text
from warpavatar.fit.presets import preset_names, preset_values

__all__ = ["add_config_arguments", "config_from_arguments"]


def _flag(name: str) -> str:
    return name.replace("_", "-")


def _finite_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise ValueError(text)
    return value


_finite_float.__name__ = "finite float"  # argparse's message: "invalid finite float value: 'nan'"


def _argument(group, f: dataclasses.Field, default_text: str, note: str = "") -> None:
    flag = "--" + _flag(f.name)
    accepted = f"; {range_text(f.name)}" if f.name in RANGES else ""
    help_text = f"{f.metadata['help']}{note} (default: {default_text}{accepted})".replace("%", "%%")
    if f.type in ("bool", bool):
        group.add_argument(flag, dest=f.name, default=None, action=argparse.BooleanOptionalAction, help=help_text)
    else:
        type_name = f.type if isinstance(f.type, str) else f.type.__name__
        kind = {"int": int, "float": _finite_float}.get(type_name, str)
        choices = f.metadata.get("choices")
        metavar = "{" + ",".join(choices) + "}" if choices else {"int": "INT", "float": "FLOAT"}.get(type_name, "STR")
        group.add_argument(flag, dest=f.name, type=kind, default=None, choices=choices, metavar=metavar,
                           help=help_text)


def add_config_arguments(parser: argparse.ArgumentParser) -> None:
    """Add one kebab-case flag per option, defaulting to "take the preset's": first the main options (core
    product options and each extension's switch and product options), then the core's groups, then one group
    per extension with its research knobs. ``--help`` shows each default and where a preset differs from it.
    """
    presets = {name: preset_values(name) for name in preset_names()}

    def shown(value) -> str:
        if isinstance(value, bool):
            return "on" if value else "off"
        return "none" if value == "" else str(value)

    def default_text(name: str, default) -> str:
        overridden = [f"{preset} preset: {shown(values[name])}" for preset, values in presets.items()
                      if name in values and values[name] != default]
        return "; ".join([shown(default)] + overridden)

    main = parser.add_argument_group("main options (each overrides the preset's value)")
    core_fields = [f for f in fields(FitConfig) if f.name != "extensions"]
    for f in core_fields:
        if f.metadata["product"]:
            _argument(main, f, default_text(f.name, f.default))
    seen: set[str] = set()
    for ext in registered():
        switch = ext.switch_name()
        seen.add(switch)
        help_text = f"{ext.summary} (default: {default_text(switch, ext.switch_default())})".replace("%", "%%")
        if ext.switch_modes:
            main.add_argument("--" + _flag(switch), dest=switch, default=None, choices=ext.switch_modes,
                              metavar="{" + ",".join(ext.switch_modes) + "}", help=help_text)
        else:
            main.add_argument("--" + _flag(switch), dest=switch, default=None,
                              action=argparse.BooleanOptionalAction, help=help_text)
        for f in fields(ext.options_type):
            if f.metadata["product"] and f.name not in seen:
                seen.add(f.name)
                _argument(main, f, default_text(f.name, f.default), note=f"; an option of --{_flag(switch)}")
    for title in CORE_GROUPS:
        group = parser.add_argument_group(f"core: {title}")
        for f in core_fields:
            if f.metadata["group"] == title and not f.metadata["product"]:
                _argument(group, f, default_text(f.name, f.default))
    owners = option_owners()
    for ext in registered():
        group = parser.add_argument_group(ext.title or ext.name)
        for f in fields(ext.options_type):
            if f.name in seen:
                continue
            seen.add(f.name)
            others = [o for o in owners[f.name] if o is not ext]
            note = "; also of " + ", ".join("--" + _flag(o.switch_name()) for o in others) if others else ""
            _argument(group, f, default_text(f.name, f.default), note=note)


def config_from_arguments(args: argparse.Namespace, preset_name: str) -> FitConfig:
    """The preset with every flag the user gave applied.

    Raises:
        ValueError: an option given for extensions that are all off.
    """
    names = ({f.name for f in fields(FitConfig)} | {ext.switch_name() for ext in registered()}
             | set(option_owners()))
    overrides = {name: getattr(args, name) for name in names if getattr(args, name, None) is not None}
    config = FitConfig.from_flat({**preset_values(preset_name), **overrides})
    for name, owners in option_owners().items():
        if name in overrides and not any(config.enabled(ext.name) for ext in owners):
            switches = " or ".join("--" + _flag(ext.switch_name()) for ext in owners)
            raise ValueError(f"--{_flag(name)} is an option of {switches}, which is off")
    return config
