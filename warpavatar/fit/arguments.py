"""The ``warpavatar-fit`` flags: one kebab-case flag per core field, extension switch and extension option, and
the two helps: ``--help`` (the main options and examples) and ``--help-all`` (every flag, by group: the main
options, the core's groups, then one group per extension, the experimental ones saying so)."""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
from dataclasses import fields

from warpavatar.extensions import get_extension, registered
from warpavatar.fit.config import CORE_GROUPS, RANGES, FitConfig, option_owners, range_text
from warpavatar.fit.presets import preset_names, preset_values

__all__ = ["HELP_OPTIONS", "EXPERIMENTAL_PARTS", "MAIN_GROUP", "add_config_arguments", "config_from_arguments",
           "main_option", "add_help_options", "skipped_stages", "schedule_warning"]

HELP_OPTIONS = {
    "iterations": "optimizer steps, one training frame each [steps]",
    "max_gaussians": "the most Gaussians the fit holds: a hard cap [Gaussians]",
    "seed": "random seed (on the CPU a fit is deterministic for a seed)",
    "sh_degree": "spherical-harmonics degree of the colours, 0-3 (0: view-independent)",
    "image_scale": "resize the training frames by this factor (the intrinsics follow)",
    "refine_poses": "refine the training poses with the avatar: 'auto' where meta.json says they are "
                    "estimated, 'on', 'off'",
    "garment": "detect loose garments and simulate them as cloth: 'auto' or 'off'; experimental",
}
"""The configuration's flags that ``--help`` shows, in order, after the command's own main options, with the short
text it shows for each (``--help-all`` shows the full one); both end with the default."""

EXPERIMENTAL_PARTS = ("garment", "dynamics", "secondary_motion", "backward_mapping", "joint_growth", "lighting")
"""The extensions whose ``--help-all`` group (and main flag) says "experimental": off in every preset, their
results still being measured (BENCHMARKS.md). Pose refinement and the pose correction, which presets turn on,
are not among them."""

MAIN_GROUP = "main options"
"""The title of the group that holds the options ``--help`` shows."""

_SHOWN_BY_HELP = "shown_by_help"  # the attribute that marks an argparse action as a main option


def _flag(name: str) -> str:
    return name.replace("_", "-")


def _finite_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise ValueError(text)
    return value


_finite_float.__name__ = "finite float"  # argparse's message: "invalid finite float value: 'nan'"

_INT64 = (-2**63, 2**63 - 1)  # what torch and numpy take: a larger integer overflows in them, far from the flag


def _int64(text: str) -> int:
    value = int(text)
    if not _INT64[0] <= value <= _INT64[1]:
        raise argparse.ArgumentTypeError(f"{text} does not fit in 64 bits (integers {_INT64[0]} to {_INT64[1]})")
    return value


_int64.__name__ = "integer"  # argparse's message: "invalid integer value: 'x'"


def main_option(action: argparse.Action, *, short: str | None = None) -> argparse.Action:
    """Mark an argparse action (what ``add_argument`` returns) as a main option, which ``--help`` shows with its own
    help or, given, the ``short`` text (``--help-all`` always with its own)."""
    setattr(action, _SHOWN_BY_HELP, action.help if short is None else short)
    return action


def _argument(group, f: dataclasses.Field, default_text: str, note: str = "") -> argparse.Action:
    flag = "--" + _flag(f.name)
    accepted = f"; {range_text(f.name)}" if f.name in RANGES else ""
    help_text = f"{f.metadata['help']}{note} (default: {default_text}{accepted})".replace("%", "%%")
    if f.type in ("bool", bool):
        return group.add_argument(flag, dest=f.name, default=None, action=argparse.BooleanOptionalAction,
                                  help=help_text)
    type_name = f.type if isinstance(f.type, str) else f.type.__name__
    kind = {"int": _int64, "float": _finite_float}.get(type_name, str)
    choices = f.metadata.get("choices")
    metavar = "{" + ",".join(choices) + "}" if choices else {"int": "INT", "float": "FLOAT"}.get(type_name, "STR")
    return group.add_argument(flag, dest=f.name, type=kind, default=None, choices=choices, metavar=metavar,
                              help=help_text)


def _switch(group, ext, default_text: str) -> argparse.Action:
    """The flag that turns extension ``ext`` on or off (or chooses its mode)."""
    switch = ext.switch_name()
    experimental = "; experimental" if ext.name in EXPERIMENTAL_PARTS else ""
    help_text = f"{ext.summary}{experimental} (default: {default_text})".replace("%", "%%")
    if ext.switch_modes:
        return group.add_argument("--" + _flag(switch), dest=switch, default=None, choices=ext.switch_modes,
                                  metavar="{" + ",".join(ext.switch_modes) + "}", help=help_text)
    return group.add_argument("--" + _flag(switch), dest=switch, default=None, action=argparse.BooleanOptionalAction,
                              help=help_text)


def _product_first(items: list[dataclasses.Field]) -> list[dataclasses.Field]:
    """Fields in their declared order, the product options (those a user is likely to set) first."""
    return sorted(items, key=lambda f: not f.metadata.get("product", False))


def add_config_arguments(parser: argparse.ArgumentParser, *, main=None) -> None:
    """Add one kebab-case flag per option, defaulting to "take the preset's": the flags of :data:`HELP_OPTIONS`
    to ``main`` (an argument group; a new one titled :data:`MAIN_GROUP` when None), marked as main options
    (:func:`main_option`), then one group per core group (``core: ...``), then one group per extension (its
    switch first; the groups of :data:`EXPERIMENTAL_PARTS` titled ``experimental: ...``). Every flag's help ends
    with its default and where a preset differs from it.
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

    core_fields = {f.name: f for f in fields(FitConfig) if f.name != "extensions"}
    switches = {ext.switch_name(): ext for ext in registered()}
    main = parser.add_argument_group(MAIN_GROUP) if main is None else main
    for name, short in HELP_OPTIONS.items():
        if name in core_fields:
            default = default_text(name, core_fields[name].default)
            action = _argument(main, core_fields[name], default)
        elif name in switches:
            default = default_text(name, switches[name].switch_default())
            action = _switch(main, switches[name], default)
        else:
            continue
        main_option(action, short=f"{short} (default: {default})".replace("%", "%%"))
    for title in CORE_GROUPS:
        group = parser.add_argument_group(f"core: {title}")
        for f in _product_first([f for f in core_fields.values() if f.metadata["group"] == title]):
            if f.name not in HELP_OPTIONS:
                _argument(group, f, default_text(f.name, f.default))
    owners = option_owners()
    seen: set[str] = set()
    for ext in registered():
        title = ext.title or ext.name
        group = parser.add_argument_group(f"experimental: {title}" if ext.name in EXPERIMENTAL_PARTS else title)
        if ext.switch_name() not in HELP_OPTIONS:
            _switch(group, ext, default_text(ext.switch_name(), ext.switch_default()))
        for f in _product_first(list(fields(ext.options_type))):
            if f.name in seen or f.name not in owners:  # (a switch's word is the switch, not an option)
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


# ------------------------------------------------------------------------------------------------ the two helps
class _HelpAction(argparse.Action):
    """``-h``/``--help`` (``every`` False): the summary, the main options and examples; ``--help-all``
    (``every`` True): the parser's whole help. Either prints and exits."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS, help=None, *,
                 every: bool, summary: str = "", examples: tuple = (), part_groups: bool = True):
        super().__init__(option_strings, dest=dest, default=default, nargs=0, help=help)
        self.every, self.summary, self.examples, self.part_groups = every, summary, examples, part_groups

    def __call__(self, parser, namespace, values, option_string=None):
        parser._print_message(parser.format_help() if self.every else self.short_help(parser), sys.stdout)
        parser.exit()

    def short_help(self, parser: argparse.ArgumentParser) -> str:
        """The usage, the summary, the main options (with their short texts) and the examples."""
        shown = [action for action in parser._actions if getattr(action, _SHOWN_BY_HELP, None) is not None]
        count = sum(1 for action in parser._actions if action.option_strings and action.help is not argparse.SUPPRESS)
        formatter = parser._get_formatter()
        formatter.add_usage(parser.usage, parser._actions, parser._mutually_exclusive_groups)
        formatter.add_text(self.summary)
        formatter.start_section(MAIN_GROUP)
        formatter.add_arguments(shown)
        formatter.end_section()
        formatter.add_text("examples:\n" + "\n".join(f"  # {comment}\n  {command}"
                                                     for command, comment in self.examples))
        formatter.add_text(f"--help-all shows all {count} options by group" + (
            "; the groups of experimental\nparts say so." if self.part_groups else "."))
        full = [action.help for action in shown]
        try:  # (the formatter reads the texts when it formats)
            for action in shown:
                action.help = getattr(action, _SHOWN_BY_HELP)
            return formatter.format_help()
        finally:
            for action, text in zip(shown, full):
                action.help = text


def add_help_options(group, *, summary: str, examples: tuple[tuple[str, str], ...], part_groups: bool = True
                     ) -> None:
    """Add ``-h``/``--help`` and ``--help-all`` to ``group`` (of a parser made with ``add_help=False`` and a
    raw-description formatter), both main options.

    Args:
        group: the argument group of the main options.
        summary: what ``--help`` prints above the main options (wrapped by the caller; the parser's description
            is ``--help-all``'s).
        examples: ``(command, comment)`` pairs that ``--help`` prints below them.
        part_groups: the command has a group of options per optional part (``--help`` says the experimental ones
            are marked).
    """
    main_option(group.add_argument("-h", "--help", action=_HelpAction, every=False, summary=summary,
                                   examples=examples, part_groups=part_groups, help="show the main options and examples, and exit"))
    main_option(group.add_argument("--help-all", action=_HelpAction, every=True,
                                   help="show every option, by group, with its unit and default, and exit"))


# ------------------------------------------------------------------------------------------- the schedule's stages
def skipped_stages(config: FitConfig) -> list[str]:
    """The stages of the schedule that ``config.iterations`` steps end before: each as ``"<stage> (step N,
    --flag)"``, in the order they would start. Stages that no length of fit reaches (a densification window with
    no round in it) are not listed.

    The steps are numbered from 0 (after the skinning field's warm-up, which runs before them): a stage that starts
    at step N runs when N < ``iterations``.
    """
    stages: list[tuple[int, str, str]] = []  # (first step, stage, flag that sets it)
    stages.append((config.gaussian_only_steps, "the skinning field's training", "--gaussian-only-steps"))
    every = config.densify_every
    first_round = max(config.densify_from, 1) + (-max(config.densify_from, 1)) % every
    if first_round <= config.densify_until:
        stages.append((first_round, "densification", "--densify-from"))
    reset = config.opacity_reset_every
    if reset and reset <= config.densify_until:
        stages.append((reset, "opacity resets", "--opacity-reset-every"))
    for degree in range(1, config.sh_degree + 1):
        stages.append((degree * config.sh_increase_every, f"SH degree {degree}", "--sh-increase-every"))
    for name, options in config.extensions.items():
        part = (get_extension(name).title or name).split(" (")[0]  # its title without the flags
        for f in fields(options):
            if f.name.endswith(("_from", "_at")) and isinstance(getattr(options, f.name), int):
                stages.append((getattr(options, f.name), part, "--" + _flag(f.name)))
    unique = {(step, stage, flag) for step, stage, flag in stages if step >= config.iterations}
    return [f"{stage} (step {step}, {flag})" for step, stage, flag in sorted(unique)]


def schedule_warning(config: FitConfig) -> str | None:
    """One line saying which stages ``config.iterations`` ends before (:func:`skipped_stages`), or None."""
    skipped = skipped_stages(config)
    if not skipped:
        return None
    return (f"warning: --iterations {config.iterations} ends before these stages start, so they never run: "
            + "; ".join(skipped))
