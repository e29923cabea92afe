"""``warpavatar-fit --help`` and ``warpavatar-fit-many --help``: the main options and two examples in one screen;
``--help-all``: every flag by group, the experimental parts' groups saying so, each option with its default; and
the one-line warning of a fit too short for its schedule's stages."""

import re
from dataclasses import fields

import pytest

from warpavatar import data
from warpavatar.cli import fit as fit_cli
from warpavatar.cli import fit_many as fit_many_cli
from warpavatar.extensions import registered
from warpavatar.fit import FitConfig, preset
from warpavatar.fit.arguments import EXPERIMENTAL_PARTS, HELP_OPTIONS, MAIN_GROUP, schedule_warning, skipped_stages
from warpavatar.fit.config import option_owners

COMMANDS = {"warpavatar-fit": fit_cli, "warpavatar-fit-many": fit_many_cli}
OPTION_LINE = re.compile(r"^  (-\w|--[\w-]+|[A-Za-z_]+(?=\s|$))")  # an entry of the help: a flag or a positional


def _printed(module, argv, capsys, monkeypatch) -> str:
    monkeypatch.setenv("COLUMNS", "80")  # argparse wraps at the terminal's width: measure at the usual 80
    with pytest.raises(SystemExit) as exit_info:
        module.build_parser().parse_args(argv)
    assert exit_info.value.code == 0
    captured = capsys.readouterr()
    assert captured.err == ""
    return captured.out


def _every_config_flag() -> set[str]:
    names = {f.name for f in fields(FitConfig) if f.name != "extensions"}
    names |= {ext.switch_name() for ext in registered()} | set(option_owners())
    return {"--" + name.replace("_", "-") for name in names}


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_help_shows_the_main_options_and_two_examples_in_80_lines(command, capsys, monkeypatch):
    text = _printed(COMMANDS[command], ["--help"], capsys, monkeypatch)
    lines = text.splitlines()
    assert len(lines) <= 80 and max(len(line) for line in lines) <= 80
    sections = [line for line in lines if line.endswith(":") and not line.startswith(" ")]
    assert sections == [f"{MAIN_GROUP}:", "examples:"]
    entries = [line for line in lines if OPTION_LINE.match(line) and not line.startswith(f"  {command}")]
    assert 10 <= len(entries) <= 20, entries
    shown = {match for line in entries for match in re.findall(r"--[\w-]+", line.split("  ")[1])}
    for name in HELP_OPTIONS:
        assert "--" + name.replace("_", "-") in shown
    assert {"--help-all", "--preset", "--device", "--no-progress"} <= shown
    assert "--lr-position" not in text and "--garment-voxel" not in text  # research knobs wait for --help-all
    examples = [line.strip() for line in lines[lines.index("examples:"):] if line.strip().startswith(command)]
    assert len(examples) == 2


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_help_all_lists_every_config_flag_by_group(command, capsys, monkeypatch):
    text = _printed(COMMANDS[command], ["--help-all"], capsys, monkeypatch)
    listed = set(re.findall(r"(?<![\w-])--[a-z][\w-]*", text))
    missing = sorted(_every_config_flag() - listed)
    assert missing == []
    groups = [line[:-1] for line in text.splitlines() if line.endswith(":") and not line.startswith(" ")]
    assert groups[0] == MAIN_GROUP and "core: density control" in groups
    assert "--help-all shows all" not in text  # (--help's last line)
    parser = COMMANDS[command].build_parser()
    options = [action for action in parser._actions if action.option_strings]
    short = _printed(COMMANDS[command], ["-h"], capsys, monkeypatch)
    assert f"--help-all shows all {len(options)} options by group" in short


def test_every_option_says_its_default():
    for module in COMMANDS.values():
        for action in module.build_parser()._actions:
            if action.dest in ("help", "help_all"):
                continue
            assert "(default: " in action.help or "no default)" in action.help, (action.option_strings, action.help)
            shown = getattr(action, "shown_by_help", None)
            assert shown is None or "(default: " in shown or "no default)" in shown, action.option_strings


def test_the_groups_of_experimental_parts_say_so():
    titles = {group.title for group in fit_cli.build_parser()._action_groups}
    for ext in registered():
        title = ext.title or ext.name
        if ext.name in EXPERIMENTAL_PARTS:
            assert f"experimental: {title}" in titles and title not in titles
        else:
            assert title in titles and f"experimental: {title}" not in titles
    assert "pose_refinement" not in EXPERIMENTAL_PARTS and "pose_correction" not in EXPERIMENTAL_PARTS
    assert {"garment", "dynamics", "secondary_motion", "backward_mapping", "joint_growth",
            "lighting"} == set(EXPERIMENTAL_PARTS)
    garment = next(a for a in fit_cli.build_parser()._actions if a.dest == "garment")  # a main flag says so too
    assert "experimental" in garment.help and "experimental" in garment.shown_by_help


def test_device_defaults_to_cuda_where_torch_sees_one(monkeypatch):
    import torch

    for available, expected in ((True, "cuda"), (False, "cpu")):
        monkeypatch.setattr(torch.cuda, "is_available", lambda: available)
        device = next(a for a in fit_cli.build_parser()._actions if a.dest == "device")
        assert device.default == expected


def test_help_options_still_parse_as_before():
    args = fit_cli.build_parser().parse_args(["folder", "--iterations", "300", "--max-gaussians", "500",
                                              "--refine-poses", "off", "--lr-position", "1e-4"])
    config = fit_cli.config_from_arguments(args, "quick")
    assert (config.iterations, config.max_gaussians, config.lr_position) == (300, 500, 1e-4)
    assert not config.enabled("pose_refinement")


# ------------------------------------------------------------------------------------ a schedule cut short
def test_a_fit_too_short_for_its_stages_names_each_stage_skipped():
    assert skipped_stages(preset("quick", iterations=300)) == [
        "pose refinement (step 400, --refine-poses-from)",
        "the skinning field's training (step 600, --gaussian-only-steps)",
        "SH degree 1 (step 800, --sh-increase-every)"]
    assert skipped_stages(preset("quick", iterations=150, garment="auto")) == [
        "densification (step 200, --densify-from)",
        "pose refinement (step 400, --refine-poses-from)",
        "the skinning field's training (step 600, --gaussian-only-steps)",
        "SH degree 1 (step 800, --sh-increase-every)",
        "simulated garments (step 1200, --garment-from)"]
    # a stage that starts at the last step still runs; one at the step after it does not
    assert "SH degree 1" not in " ".join(skipped_stages(preset("quick", iterations=801)))
    assert "SH degree 1 (step 800" in " ".join(skipped_stages(preset("quick", iterations=800)))
    warning = schedule_warning(preset("quick", iterations=300))
    assert warning.startswith("warning: --iterations 300 ends before these stages start, so they never run: ")
    assert "\n" not in warning


@pytest.mark.parametrize("name", ["default", "quick", "demo"])
def test_the_presets_run_every_stage(name):
    assert skipped_stages(preset(name)) == [] and schedule_warning(preset(name)) is None


def test_the_command_warns_in_one_line_once_its_inputs_are_read(tmp_path, capsys):
    tiny = ["--device", "cpu", "--preset", "quick", "--max-train-frames", "4", "--field-warmup-steps", "1",
            "--init-carve-candidates", "2000", "--preview-frames", "0", "--no-progress", "--refine-poses", "off"]
    # bad input: the error alone
    assert fit_cli.main([str(tmp_path / "nowhere"), "-o", str(tmp_path / "none"), "--iterations", "300", *tiny]) == 2
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and "nowhere" in lines[0]
    folder = str(data.demo_subject_path() / "train")
    assert fit_cli.main([folder, "-o", str(tmp_path / "short"), "--iterations", "2", *tiny]) == 0
    warnings = [line for line in capsys.readouterr().err.splitlines() if line.startswith("warning: ")]
    config = preset("quick", iterations=2, max_train_frames=4, field_warmup_steps=1, init_carve_candidates=2000,
                    preview_frames=0, refine_poses="off")
    assert warnings == [schedule_warning(config)] and "densification (step 200, --densify-from)" in warnings[0]
