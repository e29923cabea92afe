"""The extension protocol: an extension written outside the package plugs in without touching the trainer (the
worked example of docs/architecture.md, run as written), conflicts and requirements are refused clearly, the
registry keeps names and options apart, and avatar files of the earlier format still load."""

import dataclasses
import importlib
import json
import re
import sys
from pathlib import Path

import pytest
import torch

from warpavatar import data
from warpavatar.extensions import Extension, LossTerm, NoOptions, option, register, registered, unregister
from warpavatar.fit import Trainer, preset, preset_values
from warpavatar.model import Avatar

DOCS = Path(__file__).resolve().parents[1] / "docs" / "architecture.md"
LEGACY = Path(__file__).resolve().parent / "data" / "legacy_avatar"


def _tiny(**overrides):
    values = dict(iterations=30, image_scale=0.5, max_train_frames=6, init_points_per_bone=20,
                  init_carve_candidates=8000, init_carve_points=600, sh_degree=1, grid_cells=12, grid_min_cells=4,
                  field_hidden=16, field_layers=1, field_warmup_steps=10, gaussian_only_steps=10, densify_from=8,
                  densify_every=8, densify_until=24, checkpoint_every=1000, log_every=5, preview_frames=1)
    values.update(overrides)
    return preset("quick", **values)


@pytest.fixture(scope="module")
def video():
    return data.load_video_folder(data.demo_subject_path() / "train", max_frames=8, scale=0.5)


@pytest.fixture
def exposure_module(tmp_path, monkeypatch):
    """The worked example of docs/architecture.md, written to a module of its own and imported (registered)."""
    blocks = re.findall(r"```python\n(.*?)```", DOCS.read_text(), flags=re.S)
    example = next(block for block in blocks if "class ExposureExtension" in block)
    assert len(example.strip().splitlines()) <= 70  # a worked example, not a module
    (tmp_path / "exposure_example.py").write_text(example)
    monkeypatch.syspath_prepend(str(tmp_path))
    module = importlib.import_module("exposure_example")
    yield module
    unregister("exposure")
    sys.modules.pop("exposure_example", None)


def test_the_documented_extension_plugs_in_without_touching_the_trainer(exposure_module, video, tmp_path):
    assert [cls.name for cls in registered()][-1] == "exposure"
    config = _tiny(exposure=True, lr_exposure=5e-2)
    assert config.enabled("exposure") and config.extensions["exposure"].lr_exposure == 5e-2
    trainer = Trainer(video, config, tmp_path / "fit")
    part = trainer.avatar.part("exposure")
    assert isinstance(part, exposure_module.FrameExposure) and part.log_gain.shape == (trainer.frames.count, 3)
    trainer.fit(progress=False)
    # it trained: gains moved on the frames that were seen, its loss term is logged by name
    assert float(part.log_gain.detach().abs().max()) > 1e-3
    log = [json.loads(line) for line in (tmp_path / "fit" / "train_log.jsonl").read_text().splitlines()]
    assert all("exposure" in entry for entry in log if "loss" in entry)
    # the fit's render of a training frame uses that frame's gain; a plain render (novel pose or view) none
    index = 2
    frames = trainer.frames
    bones = frames.bone_transforms[index]
    with torch.no_grad():
        plain, _, _ = trainer.avatar.render(frames.cameras[index], bones, background=frames.background)
        exposed, _, _ = trainer.avatar.render(frames.cameras[index], bones, background=frames.background,
                                              inputs={"exposure": index})
    assert (plain - exposed).abs().max() > 1e-4
    # the avatar file carries the part, rebuilt from its class path
    loaded = Avatar.load(tmp_path / "fit")
    assert torch.equal(loaded.part("exposure").log_gain, part.log_gain)
    with torch.no_grad():
        again, _, _ = loaded.render(frames.cameras[index], bones.cpu(), background=frames.background,
                                    inputs={"exposure": index})
    assert torch.allclose(again, exposed, atol=1e-5)


def test_a_plugged_in_extension_resumes_exactly(exposure_module, video, tmp_path):
    config = _tiny(exposure=True, lr_exposure=5e-2)
    whole = Trainer(video, config, tmp_path / "whole")
    whole.fit(progress=False)
    Trainer(video, config, tmp_path / "parts").fit(progress=False, stop_at=17)
    resumed = Trainer(video, config, tmp_path / "parts")
    resumed.fit(resume=True, progress=False)
    assert torch.allclose(whole.avatar.part("exposure").log_gain, resumed.avatar.part("exposure").log_gain, atol=1e-6)
    assert torch.allclose(whole.gaussians.means, resumed.gaussians.means, atol=1e-6)


def test_the_command_line_gets_a_plugged_in_extension(exposure_module):
    from warpavatar.cli.fit import build_parser
    from warpavatar.fit.arguments import config_from_arguments

    parser = build_parser()
    text = parser.format_help()
    assert "per-frame exposure (--exposure):" in text and "--lr-exposure" in text
    config = config_from_arguments(parser.parse_args(["x", "--exposure", "--lambda-exposure", "0.5"]), "quick")
    assert config.extensions["exposure"].lambda_exposure == 0.5
    with pytest.raises(ValueError, match="--lambda-exposure is an option of --exposure, which is off"):
        config_from_arguments(parser.parse_args(["x", "--lambda-exposure", "0.5"]), "quick")


@dataclasses.dataclass
class _SpinOptions:
    spin_weight: float = option(1.0, "weight")


def _extension(name, **attributes):
    return type(name.title() + "Extension", (Extension,), {"name": name, **attributes})


def test_conflicting_and_missing_extensions_are_refused_clearly():
    with pytest.raises(ValueError, match="choose one secondary-motion model"):
        preset("quick", dynamics=True, secondary_motion=True)
    first = _extension("spin", options_type=_SpinOptions, conflicts={"lighting": "--spin moves the lights: "
                                                                                 "drop --lighting"})
    second = _extension("tilt", requires=("spin",))
    register(first)
    register(second)
    try:
        with pytest.raises(ValueError, match="--spin moves the lights: drop --lighting"):
            preset("quick", spin=True, lighting=True)
        with pytest.raises(ValueError, match="--tilt needs --spin"):
            preset("quick", tilt=True)
        config = preset("quick", spin=True, tilt=True, spin_weight=2.0, refine_poses="off")
        assert list(config.extensions) == ["spin", "tilt"]
    finally:
        unregister("tilt")
        unregister("spin")


def test_the_registry_keeps_names_and_options_apart():
    with pytest.raises(ValueError, match="called 'dynamics' is registered already"):
        register(_extension("dynamics"))

    @dataclasses.dataclass
    class Clashing:
        frame_codes: int = option(3, "a clash with the pose correction's option")

    with pytest.raises(ValueError, match="option 'frame_codes'"):
        register(_extension("clash", options_type=Clashing))
    assert "clash" not in [cls.name for cls in registered()]
    with pytest.raises(ValueError, match="unknown config fields: \\['not_an_option'\\]"):
        preset("quick", not_an_option=1)
    with pytest.raises(ValueError, match="unknown extension 'nonesuch'"):
        preset("quick").__class__.from_dict({**preset("quick").to_dict(), "extensions": {"nonesuch": {}}})


def test_config_round_trips_and_reads_the_flat_layout_of_earlier_versions():
    config = preset("quick", dynamics=True, dynamics_hidden=16, lighting=True, pose_correction=True)
    assert type(config).from_dict(config.to_dict()) == config
    assert list(config.extensions) == ["pose_refinement", "pose_correction", "dynamics", "lighting"]  # registry order
    # an earlier config.json: every field at the top level, extensions switched by booleans
    flat = preset_values("quick")
    flat.update(dynamics=True, dynamics_hidden=16, lighting=True, pose_correction=True, secondary_motion=False,
                grow_joints=False, backward_mapping=False)  # an earlier file has no refine_poses: 'auto' it is
    assert type(config).from_dict(flat) == config
    with pytest.raises(ValueError, match="shading must be 'world' or 'view'"):
        preset("quick", shading="lambert")


def test_every_hook_is_called_in_order(video, tmp_path):
    calls = []

    class Recorder(Extension):
        name = "recorder"
        options_type = NoOptions

        def attach(self):
            calls.append("attach")

        def begin_step(self, step):
            calls.append(f"begin {step.step}")

        def frame_input(self, step):
            calls.append("input")

        def losses(self, step):
            calls.append("losses")
            assert step.image is not None and step.posed["means"].shape[0] == self.fit.avatar.gaussians.count
            return {"recorded": LossTerm(0.0, step.image.mean())}

        def after_backward(self, step):
            calls.append("after_backward")

        def before_densify(self, visible_count):
            calls.append(f"before_densify {visible_count.shape[0]}")

        def on_gaussians_renumbered(self, source_index):
            assert source_index.shape[0] == self.fit.avatar.gaussians.count
            calls.append("renumbered")

        def finish(self):
            calls.append("finish")

    register(Recorder)
    try:
        Trainer(video, _tiny(recorder=True, iterations=9), tmp_path / "fit").fit(progress=False)
    finally:
        unregister("recorder")
    assert calls[:5] == ["attach", "begin 0", "input", "losses", "after_backward"]
    round_start = calls.index("begin 8") + 4
    assert calls[round_start].startswith("before_densify") and calls[round_start + 1] == "renumbered"
    assert calls[-1] == "finish"


@pytest.mark.parametrize("name", ["parts", "dynamics"])
def test_avatar_files_of_format_1_still_load_and_render_the_same(name):
    """Files written by warpavatar before the extension protocol (one key per optional part), with their renders
    from that version (tests/data/legacy_avatar/README.md)."""
    avatar = Avatar.load(LEGACY / f"{name}_v1.pt")
    expected = torch.load(LEGACY / "renders_v1.pt", weights_only=True)[name]
    video = data.load_video_folder(data.demo_subject_path() / "train", max_frames=6, scale=0.25)
    bones = torch.as_tensor(video.bone_transforms, dtype=torch.float32)
    with torch.no_grad():
        renders = torch.stack([avatar.render(video.cameras[i], bones[i])[0] for i in (1, 4)])
    assert torch.allclose(renders, expected, atol=1e-5)
    if name == "parts":
        assert list(avatar.parts) == ["joint_growth", "pose_correction", "secondary_motion", "lighting"]
        assert avatar.grown_joint_count == 2 and avatar.shading_origin is not None
    else:
        assert list(avatar.parts) == ["dynamics"]


def test_unreadable_avatar_files_are_clear_errors(tmp_path):
    torch.save({"format": "warpavatar-avatar/9"}, tmp_path / "future.pt")
    with pytest.raises(ValueError, match="format 'warpavatar-avatar/9'"):
        Avatar.load(tmp_path / "future.pt")
    state = torch.load(LEGACY / "parts_v1.pt", weights_only=True)
    state["pose_correction"] = None
    torch.save(state, tmp_path / "damaged.pt")  # grown joints without the pose correction is fine ...
    Avatar.load(tmp_path / "damaged.pt")
    del state["field"]
    torch.save(state, tmp_path / "broken.pt")  # ... a missing skinning field is not
    with pytest.raises(ValueError, match="broken.pt: a damaged or incomplete avatar file"):
        Avatar.load(tmp_path / "broken.pt")
    upgraded = torch.load(LEGACY / "parts_v1.pt", weights_only=True)
    upgraded = Avatar.load(LEGACY / "parts_v1.pt").state_for_file()
    upgraded["parts"]["lighting"]["type"] = "warpavatar.nonesuch:Light"
    torch.save(upgraded, tmp_path / "plugin.pt")
    with pytest.raises(ValueError, match="part 'lighting' needs 'warpavatar.nonesuch:Light'"):
        Avatar.load(tmp_path / "plugin.pt")
