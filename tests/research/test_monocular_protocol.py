"""The alignment of research/monocular_protocol.py: a similarity transform from skeletons, and calibrated cameras
carried into the monocular world without changing what they see."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from research import monocular_protocol

pytestmark = pytest.mark.research


def _tool():
    return monocular_protocol


def test_similarity_transform_recovers_a_known_one_and_rejects_degenerate_points():
    tool = _tool()
    generator = np.random.default_rng(0)
    points = generator.normal(size=(60, 3))
    rotation = Rotation.random(random_state=1).as_matrix()
    mapped = 1.7 * points @ rotation.T + np.array([0.3, -2.0, 5.0])
    scale, found, translation = tool.similarity_transform(points, mapped)
    assert scale == pytest.approx(1.7, rel=1e-10)
    assert np.allclose(found, rotation, atol=1e-10) and np.isclose(np.linalg.det(found), 1.0)
    assert np.allclose(translation, [0.3, -2.0, 5.0], atol=1e-10)
    # with noise it is the least-squares fit: the residual is no larger than for the true transform
    noisy = mapped + 0.05 * generator.normal(size=mapped.shape)
    scale, found, translation = tool.similarity_transform(points, noisy)
    fitted = ((scale * points @ found.T + translation - noisy) ** 2).sum()
    assert fitted <= ((mapped - noisy) ** 2).sum() + 1e-9
    # a mirror image is not a rotation: the result stays proper
    _, mirrored, _ = tool.similarity_transform(points, points * np.array([-1.0, 1.0, 1.0]))
    assert np.isclose(np.linalg.det(mirrored), 1.0)
    with pytest.raises(ValueError, match="span a plane"):
        tool.similarity_transform(np.outer(np.arange(5.0), [1.0, 2.0, 3.0]), generator.normal(size=(5, 3)))
    with pytest.raises(ValueError, match="matching"):
        tool.similarity_transform(points[:2], mapped[:2])


def test_a_camera_carried_into_the_monocular_world_sees_the_same_pixels():
    tool = _tool()
    generator = np.random.default_rng(2)
    rotation, scale, translation = Rotation.random(random_state=3).as_matrix(), 0.8, np.array([1.0, 0.5, -0.2])
    world_to_camera = np.eye(4)
    world_to_camera[:3, :3] = Rotation.random(random_state=4).as_matrix()
    world_to_camera[:3, 3] = [0.1, 0.2, 6.0]
    K = np.array([[900.0, 0.0, 288.0], [0.0, 900.0, 512.0], [0.0, 0.0, 1.0]])
    mono_points = 0.5 * generator.normal(size=(20, 3))
    calibrated_points = scale * mono_points @ rotation.T + translation

    def project(points, w2c):
        local = points @ w2c[:3, :3].T + w2c[:3, 3]
        pixels = local @ K.T
        return pixels[:, :2] / pixels[:, 2:]

    carried = tool.camera_into_monocular_world(world_to_camera, scale, rotation, translation)
    assert np.allclose(carried[:3, :3] @ carried[:3, :3].T, np.eye(3), atol=1e-12)  # still rigid
    assert np.allclose(project(mono_points, carried), project(calibrated_points, world_to_camera), atol=1e-9)


def test_the_subjects_withhold_the_same_instants_and_the_oracle_keeps_the_calibrated_poses(tmp_path):
    """Both subjects of the protocol from one calibrated subject (the bundled demo, standing in for both the
    monocular and the calibrated preparation): the same instants withheld, novel views only at training instants;
    the oracle keeps the calibrated poses and cameras, and a monocular world that is the calibrated one aligns
    with scale 1 and leaves every camera where it was."""
    from warpavatar import data

    tool = _tool()
    demo = data.load_subject(data.demo_subject_path(), scale=0.25)
    ids = demo.train.frame_ids.tolist()
    oracle_info = tool.build_oracle_subject(demo, tmp_path / "oracle", train_camera="front", holdout_every=5)
    aligned = tool.build_evaluation_subject(demo.train, demo, tmp_path / "subject", train_camera="front",
                                            holdout_every=5)
    assert aligned["scale"] == pytest.approx(1.0, abs=1e-6) and aligned["alignment_rms"] < 1e-5
    held = [i for i in ids if i % 5 == 2]
    assert oracle_info["held_out_frames"] == aligned["held_out_frames"] == len(held) > 0
    for folder in ("oracle", "subject"):
        subject = data.load_subject(tmp_path / folder)
        assert subject.train.frame_ids.tolist() == [i for i in ids if i % 5 != 2]
        heldout = subject.novel_view["front_heldout"]
        assert heldout.frame_ids.tolist() == held
        view = subject.novel_view["cam_090"]
        source = demo.novel_view["cam_090"]
        kept = [row for row, i in enumerate(source.frame_ids.tolist()) if i in set(subject.train.frame_ids.tolist())]
        assert view.frame_ids.tolist() == source.frame_ids[kept].tolist() and 0 < len(kept) < source.frame_count
        for camera, original in zip(view.cameras, [source.cameras[row] for row in kept]):
            assert np.allclose(camera.world_to_camera, original.world_to_camera, atol=1e-4)
        train_rows = [ids.index(i) for i in view.frame_ids.tolist()]
        # the oracle's poses are the calibrated subject's own; the monocular subject's come from its training
        # folder (here the same skeleton, so the same poses)
        expected = source.bone_transforms[kept] if folder == "oracle" else demo.train.bone_transforms[train_rows]
        assert np.allclose(view.bone_transforms, expected, atol=1e-6)
        assert np.allclose(heldout.images, demo.train.images[[ids.index(i) for i in held]], atol=1 / 255)


def test_the_protocol_fits_the_modes_asked_and_names_the_oracle_fits_apart(tmp_path, capsys):
    """Subject fits take their mode's name, the oracle's ``off`` fit keeps the name "oracle" (earlier reports use
    it) and its other modes get their own; bad, repeated or empty mode lists are refused on one line."""
    tool = _tool()
    subject, oracle = tmp_path / "subject", tmp_path / "oracle"
    runs = tool.protocol_runs(" off, on ", "off,on", subject=subject, oracle=oracle)
    assert runs == [("off", subject, "off"), ("on", subject, "on"), ("oracle", oracle, "off"),
                    ("oracle_on", oracle, "on")]
    assert tool.protocol_runs("", "auto", subject=subject, oracle=oracle) == [("oracle_auto", oracle, "auto")]
    for modes, oracle_modes, message in (("off,maybe", "", "'maybe' is not one of off, on, auto"),
                                         ("on,on", "", "listed twice"), ("", "", "nothing to fit")):
        with pytest.raises(ValueError, match=message):
            tool.protocol_runs(modes, oracle_modes, subject=subject, oracle=oracle)
    # the command line refuses them before anything is prepared or fitted
    with pytest.raises(SystemExit) as exit_info:
        tool.main([str(tmp_path / "demo"), "-o", str(tmp_path / "out"), "--oracle", "--oracle-modes", "of"])
    assert exit_info.value.code == 2
    assert "refine mode 'of' is not one of off, on, auto" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_info:
        tool.main([str(tmp_path / "demo"), "-o", str(tmp_path / "out"), "--oracle-modes", "on"])
    assert exit_info.value.code == 2 and "--oracle-modes needs --oracle" in capsys.readouterr().err
