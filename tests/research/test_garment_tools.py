"""The garment diagnostics of research/: detection on a saved avatar (garment_report), an instant's cloth nodes
fitted to its images (garment_oracle) and the training motion rolled out again under changed physics
(garment_sweep). The fixtures and the synthetic skirt are test_garment.py's."""

import copy
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from test_garment import HEADS, PARENTS, TAILS, _motion, _panelled_skirt, _walk, forced, video  # noqa: F401

from research import garment_oracle, garment_report, garment_sweep
from warpavatar import data
from warpavatar.model.parts import frame_intervals

pytestmark = pytest.mark.research


class _NearestWeights:
    """A skinning field that gives any point the weights of the nearest of some points (a fitted field's stand-in
    for research/garment_report.py), on a grid of 2 cm voxels."""

    def __init__(self, means, weights):
        self.means, self.table = means, weights
        self.bbox_min, self.bbox_max = means.min(0).values - 0.1, means.max(0).values + 0.1
        self.grid_shape = tuple(int(c) for c in ((self.bbox_max - self.bbox_min) / 0.02).ceil().flip(0) + 1)

    def weights(self, points, grid=None):
        return self.table[torch.cdist(points, self.means).argmin(dim=1)]


def test_garment_report_tool_finds_the_skirt_its_band_and_its_waistband():
    means, weights, strip, panel = _panelled_skirt(torch.Generator().manual_seed(5))
    avatar = SimpleNamespace(gaussians=SimpleNamespace(means=means), field=_NearestWeights(means, weights),
                             skinning_groups=lambda: None)
    skeleton = data.Skeleton(["pelvis", "spine", "thigh_l", "thigh_r", "shin_l", "shin_r"], np.array(PARENTS),
                             HEADS.numpy(), TAILS.numpy())
    video = SimpleNamespace(skeleton=skeleton, bone_transforms=_walk().numpy())
    report = garment_report.garment_report(avatar, video, band=(0.32, 0.65))  # z 0.48 .. 0.98
    assert report["gaussians"] == means.shape[0] and len(report["garments"]) == 1
    garment = report["garments"][0]
    assert garment["joint"] == "pelvis" and set(garment["split"]) == {"thigh_l", "thigh_r"}
    assert garment["gaussians"] >= int((strip | panel).sum()) * 0.95 and garment["band_held"] > 0.9
    assert garment["attached_sectors_of_12"] == 12 and garment["attached_heights"][0] > 0.55  # above z 0.83


def test_the_oracle_tool_fits_an_instants_nodes_to_its_images(forced, video, tmp_path, capsys):
    trainer, _, _ = forced
    tool = garment_oracle
    subject = SimpleNamespace(train=video, novel_view={"again": video})  # a second view: the same camera again
    frame = int(video.frame_ids[0])
    avatar = copy.deepcopy(trainer.avatar)
    asked = [parameter.requires_grad for parameter in avatar.parameters()]
    values = [parameter.detach().clone() for parameter in avatar.parameters()]
    rows = tool.oracle_rows(avatar, subject, [frame], steps=20, band=(0.3, 0.9), appearance=True)
    assert [parameter.requires_grad for parameter in avatar.parameters()] == asked  # the avatar is left as it was
    assert all(torch.equal(a, b) for a, b in zip(values, avatar.parameters()))
    assert [row["mode"] for row in rows] == ["rollout", "training view", "every view", "every view + appearance"]
    rollout, single, every, looks = rows
    assert rollout["moved"] == 0.0 and single["moved"] > 0.0 and every["moved"] > 0.0 and looks["moved"] > 0.0
    assert set(rollout["psnr"]) == {"train", "again"} and rollout["psnr"]["train"] == rollout["psnr"]["again"]
    assert single["psnr"]["train"] > rollout["psnr"]["train"]  # the nodes were fitted to that image
    # The garment's colours, opacities and scales fitted too: the drawing differs from the nodes-only oracle's, and
    # after the rows the avatar draws as before.
    assert looks["psnr"]["train"] != every["psnr"]["train"]
    again = tool.oracle_rows(avatar, subject, [frame], steps=1, band=(0.3, 0.9))
    assert again[0]["psnr"] == rollout["psnr"]
    with pytest.raises(ValueError, match="not one of the fit's training frames"):
        tool.oracle_rows(copy.deepcopy(trainer.avatar), subject, [10_000], steps=1)
    bare = copy.deepcopy(trainer.avatar)
    del bare.parts["garment"]
    with pytest.raises(ValueError, match="no simulated garment"):
        tool.oracle_rows(bare, subject, [frame], steps=1)
    assert tool.main([str(tmp_path / "none.pt"), str(tmp_path / "nowhere"), "--frames", "0"]) == 2
    error = capsys.readouterr().err.strip()
    assert "nowhere" in error and "\n" not in error


def test_the_sweep_tool_rolls_changed_cloth_out_and_puts_the_fitted_one_back(forced, video, tmp_path, capsys):
    tool = garment_sweep
    assert tool.parse_variant("damping=0.01, drag=0.2") == {"damping": 0.01, "drag": 0.2}
    for spec, message in (("damping=1.5", "fraction of its bound"), ("stiffness=-1", "positive"),
                          ("wind=3", "key among"), ("flare=1.2,flare=1.3", "given twice"), ("mass=heavy", "number"),
                          ("strain=1.0", "above 1")):
        with pytest.raises(ValueError, match=message):
            tool.parse_variant(spec)
    avatar = copy.deepcopy(forced[0].avatar)
    part = avatar.part("garment")
    before = {name: tensor.clone() for name, tensor in [*part.cloth.named_parameters(), *part.cloth.named_buffers()]}
    motion = _motion(video)
    bones = torch.stack([avatar.pose_bones(b) for b in motion])
    intervals = frame_intervals(range(motion.shape[0]), 30.0).tolist()
    fitted, _ = part.rollout(bones, intervals)
    with tool.changed_cloth(part, {"damping": 0.9, "drag": 0.9, "stiffness": 3.0, "mass": 1.5, "flare": 1.4}):
        changed, _ = part.rollout(bones, intervals)
        assert float(torch.sigmoid(part.cloth.drag_logit.detach())) == pytest.approx(0.9, rel=1e-5)
    assert (changed - fitted).norm(dim=-1).max() > 1e-3  # the changes reach the rollout
    with tool.changed_cloth(part, {"flare": 1.5}):  # a wider rest shape alone hangs the cloth wider
        rest = part.cloth.rest_positions().detach()
        flared, _ = part.rollout(bones, intervals)
    up = torch.as_tensor(part.hyper["up"], dtype=torch.float32)
    up = up / up.norm()
    ring = part.cloth.initial_rest_positions[part.cloth.attached].mean(0)

    def spread(points):  # mean distance of the free nodes from the vertical axis through the ring
        offset = points - ring
        free = torch.ones(points.shape[0], dtype=torch.bool)
        free[part.cloth.attached] = False
        return (offset - (offset @ up)[:, None] * up).norm(dim=1)[free].mean()

    assert spread(rest) > spread(part.cloth.rest_positions().detach()) * 1.05
    assert spread(flared[0]) > spread(fitted[0])
    for name, tensor in [*part.cloth.named_parameters(), *part.cloth.named_buffers()]:
        assert torch.equal(tensor, before[name]), name  # and are undone after
    again, _ = part.rollout(bones, intervals)
    assert torch.equal(again, fitted)
    with tool.changed_cloth(part, {"stiffness": 1e6}):  # raised to the cap, never past it or lowered
        raised, fitted_fraction = (torch.sigmoid(logit.detach()) for logit in (part.cloth.stiffness_logit,
                                                                                before["stiffness_logit"]))
        assert bool((raised <= torch.clamp(fitted_fraction, min=tool.STIFFNESS_CAP) + 1e-6).all())
        assert bool((raised >= torch.clamp(fitted_fraction, max=tool.STIFFNESS_CAP) - 1e-6).all())
        assert float(raised.max()) > float(fitted_fraction.max())  # (the fitted springs were below the cap)
    with pytest.raises(ValueError, match="outside the cloth's range"), tool.changed_cloth(part, {"mass": 50.0}):
        pass
    assert part.cloth.strain_limit == 0.0  # strain limiting: on for the block, longest edges within the limit
    with tool.changed_cloth(part, {"strain": 1.02}):
        limited, _ = part.rollout(bones, intervals)
        assert part.cloth.strain_limit == 1.02 and part.cloth.strain_iterations == tool.STRAIN_ITERATIONS
    pairs = part.cloth.pairs[:part.cloth.stretch_count]
    rest_lengths = part.cloth.rest_lengths().detach()[:part.cloth.stretch_count]

    def worst_strain(positions):
        return float(((positions[:, pairs[:, 0]] - positions[:, pairs[:, 1]]).norm(dim=-1) / rest_lengths).max())

    assert worst_strain(limited) < worst_strain(fitted) and worst_strain(limited) < 1.1
    assert part.cloth.strain_limit == 0.0 and part.cloth.strain_iterations == 0
    assert torch.equal(part.rollout(bones, intervals)[0], fitted)
    subject = SimpleNamespace(train=video, novel_view={"again": video})  # a second view: the same camera again
    rows = tool.sweep_rows(avatar, subject, [{"stiffness": 1.0}, {"flare": 1.5, "drag": 0.5}], stride=2,
                           band=(0.3, 0.9))
    assert [row["variant"] for row in rows] == [{}, {"stiffness": 1.0}, {"flare": 1.5, "drag": 0.5}]
    same, flared = rows[1], rows[2]
    assert set(rows[0]["iou"]) == {"train", "again"} and rows[0]["iou"]["train"] == rows[0]["iou"]["again"]
    assert all(0.0 < value <= 1.0 for row in rows for value in row["iou"].values())
    assert same["psnr"]["train"] == pytest.approx(rows[0]["psnr"]["train"], abs=1e-3)  # an unchanged cloth
    assert flared["psnr"]["train"] != pytest.approx(rows[0]["psnr"]["train"], abs=1e-3)
    # the skinned row, and rows scored after re-learning the garment's appearance on the training frames: the
    # training view gains, and the avatar's appearance and flags are put back
    looks = {name: getattr(avatar.gaussians, name).detach().clone() for name in ("sh_dc", "opacity_logits")}
    flags = [parameter.requires_grad for parameter in avatar.parameters()]
    plain = tool.sweep_rows(avatar, subject, [], stride=2, band=(0.3, 0.9), skinned=True)
    relearned = tool.sweep_rows(avatar, subject, [], stride=2, band=(0.3, 0.9), skinned=True, retexture_steps=30)
    assert [row["variant"] for row in plain] == [{}, None] and plain[0]["psnr"] == rows[0]["psnr"]
    assert plain[1]["psnr"]["train"] != pytest.approx(plain[0]["psnr"]["train"], abs=1e-3)
    for before_row, after_row in zip(plain, relearned):
        assert after_row["psnr"]["train"] > before_row["psnr"]["train"] + 0.05, (before_row, after_row)
    for name, value in looks.items():
        assert torch.equal(getattr(avatar.gaussians, name), value), name
    assert [parameter.requires_grad for parameter in avatar.parameters()] == flags
    with pytest.raises(ValueError, match="retexture_steps"):
        tool.sweep_rows(avatar, subject, [], retexture_steps=-1)
    bare = copy.deepcopy(avatar)
    del bare.parts["garment"]
    with pytest.raises(ValueError, match="no simulated garment"):
        tool.sweep_rows(bare, subject, [])
    assert tool.main([str(tmp_path / "none.pt"), str(tmp_path / "nowhere")]) == 2
    error = capsys.readouterr().err.strip()
    assert "nowhere" in error and "\n" not in error
    with pytest.raises(SystemExit) as exit_info:
        tool.main([str(tmp_path / "none.pt"), str(tmp_path / "nowhere"), "--variant", "drag=2"])
    assert exit_info.value.code == 2 and "fraction of its bound" in capsys.readouterr().err
