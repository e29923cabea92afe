"""tools/mesh_benchmark.py on a tiny avatar and the demo subject: the mesh and the Gaussians scored against the
ground truth, and the silhouette IoU, written as JSON."""

import importlib.util
import json
import math

import numpy as np
import pytest
import torch

from conftest import load_tool
from warpavatar import data

TINY = ["--frames", "2", "--scale", "0.5", "--device", "cpu"]


def _check_results(path, *, stand_in: bool):
    results = json.loads(path.read_text())
    assert results["stand_in"] is stand_in
    assert list(results["rows"]) == ["train", "novel_view/cam_090", "novel_pose/dance_cam000"]
    for row in results["rows"].values():
        assert row["frame_count"] == 2 and row["resolution"] == "64x64"
        for key in ("mesh_psnr_masked", "mesh_ssim_masked", "gaussians_psnr_masked", "gaussians_ssim_masked",
                    "iou", "iou_min", "mesh_render_ms", "gaussians_render_ms"):
            assert math.isfinite(row[key]), key
        assert 0.0 <= row["iou_min"] <= row["iou"] <= 1.0
        assert 0.0 <= row["mesh_only"] and 0.0 <= row["gaussians_only"] <= 1.0
        assert len(row["frames"]) == 2
    return results


def test_measures_a_stand_in_mesh(avatar_dir, tmp_path, capsys):
    tool = load_tool("mesh_benchmark")
    output = tmp_path / "mesh.json"
    assert tool.main([str(avatar_dir), str(data.demo_subject_path()), *TINY, "--stand-in", "-o", str(output)]) == 0
    results = _check_results(output, stand_in=True)
    assert results["mesh"]["shading"] == "vertex_colors" and results["mesh"]["faces"] > 0
    # the hull of the Gaussians' centres overlaps what the (few, sparse) Gaussians cover
    assert results["rows"]["train"]["iou"] > 0.1
    printed = capsys.readouterr().out
    assert "| train | 2 |" in printed and "training-frame silhouette IoU" in printed


@pytest.mark.skipif(any(importlib.util.find_spec(f"warpavatar.mesh.{name}") is None for name in ("surface", "texture")),
                    reason="the mesh export's stages (warpavatar.mesh.surface, warpavatar.mesh.texture) are missing")
def test_measures_the_exported_mesh(avatar_dir, tmp_path):
    tool = load_tool("mesh_benchmark")
    output = tmp_path / "mesh.json"
    assert tool.main([str(avatar_dir), str(data.demo_subject_path()), *TINY, "--triangles", "2000",
                      "--texture-size", "64", "--view-count", "12", "--view-size", "64", "--supersample", "2",
                      "--max-voxels", "200000", "-o", str(output)]) == 0
    results = _check_results(output, stand_in=False)
    assert results["mesh"]["shading"] == "texture" and results["mesh"]["texture_size"] == [64, 64]
    assert results["mesh"]["view_size"] == 64 and results["mesh"]["max_voxels"] == 200000
    assert results["mesh"]["voxel_size"] > 0


def test_the_iou_and_the_frame_subset():
    tool = load_tool("mesh_benchmark")
    mesh = torch.zeros(4, 4)
    gaussians = torch.zeros(4, 4)
    mesh[:2] = 1.0
    gaussians[1:3] = 0.5  # alpha 0.5 counts as inside
    assert tool.silhouette_iou(mesh, gaussians) == pytest.approx(4 / 12)
    assert tool.silhouette_iou(torch.zeros(2, 2), torch.full((2, 2), 0.49)) == 1.0
    # rows 0 (mesh only) and 2 (Gaussians only), each 4 pixels, over the Gaussians' 8
    assert tool.silhouette_misses(mesh, gaussians) == (pytest.approx(0.5), pytest.approx(0.5))
    assert tool.silhouette_misses(mesh, torch.zeros(4, 4)) == (0.0, 0.0)
    assert tool.frame_subset(10, 3).tolist() == [0, 4, 9]
    assert np.array_equal(tool.frame_subset(3, 8), np.arange(3)) and len(tool.frame_subset(5, 0)) == 5


def test_bad_options_are_one_line_errors(avatar_dir, tmp_path, capsys):
    tool = load_tool("mesh_benchmark")
    assert tool.main([str(avatar_dir), str(data.demo_subject_path()), "--frames", "-1"]) == 2
    assert tool.main([str(avatar_dir), str(tmp_path / "missing"), "--stand-in"]) == 2
    errors = capsys.readouterr().err.splitlines()
    assert errors == ["error: --frames must be at least 0, got -1", f"error: {tmp_path / 'missing'}: is not a folder"]
