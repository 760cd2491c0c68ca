"""The half-turn's appearance cue (perception/facecue.py): the projected face polygons equal OpenCV's projection,
the softmax fit recovers a known model, the log-likelihood ratio follows the classes each naming expects of a
region and abstains where neither fits, a naming is re-weighed (and swapped) by it, and `envisat calibrate
--face-cue` stores a cue that load_detector reads back."""

import dataclasses

import cv2
import numpy as np
import pytest

from envisat_pose.geometry import FACE_COVERING, FACE_NAMES, load_geometry
from envisat_pose.perception import facecue as fc
from envisat_pose.perception.box_symmetry import face_windings
from envisat_pose.perception.naming import Naming


def test_face_polygons_are_opencvs_projection():
    g = load_geometry()
    W = face_windings(g)
    R = cv2.Rodrigues(np.array([0.4, -0.9, 0.3]))[0]
    t = np.array([0.5, -0.3, 40.0])
    K = np.array([[800.0, 0, 320.5], [0, 810.0, 240.5], [0, 0, 1]])
    poly, facing, cos = fc.face_polygons(R, t, K, g, W)
    uv = cv2.projectPoints(g.corners_T_m, cv2.Rodrigues(R)[0], t, K, None)[0][:, 0]
    np.testing.assert_allclose(poly, uv[W], atol=1e-9)
    cam_T = -R.T @ t  # the camera in T: a face is seen when it is on the outside of its plane
    np.testing.assert_array_equal(facing, g.face_normals_T @ cam_T > g.face_offsets_m)
    assert np.all(np.abs(cos) <= 1.0)


def test_half_turn_faces_and_classes():
    """The half-turn about x keeps +-x and swaps +y with -y, +z with -z; the swapped faces' classes differ."""
    assert [FACE_NAMES[k] for k in fc.HALF_TURN_FACE] == ["px", "mx", "my", "py", "mz", "pz"]
    for f, g in (("py", "my"), ("pz", "mz")):
        assert FACE_COVERING[f] != FACE_COVERING[g]
    assert [fc.CLASS_NAMES[c] for c in fc.FACE_CLASS] == [FACE_COVERING[f] for f in FACE_NAMES]


def test_softmax_fit_recovers_a_known_model():
    rng = np.random.default_rng(3)
    X = np.c_[np.ones(6000), rng.normal(size=(6000, 3))]
    W = np.array([[0.2, -0.1, 0.0], [1.5, -1.0, 0.0], [0.0, 2.0, -1.0], [-1.0, 0.5, 0.5]])
    p = np.exp(fc.log_softmax(X @ W))
    y = np.array([rng.choice(3, p=q) for q in p])
    W_fit = fc.fit_softmax(X, y, 3, l2=1e-3)
    p_fit = np.exp(fc.log_softmax(X @ W_fit))
    assert np.mean(np.abs(p_fit - p)) < 0.02


def cluster_cue():
    """A cue fitted on regions whose features sit in one cluster per covering class (well apart)."""
    rng = np.random.default_rng(5)
    centres = rng.normal(size=(len(fc.CLASS_NAMES), len(fc.FEATURES))) * 4.0
    regions = []
    for k in range(6):
        for _ in range(80):
            regions.append((k, centres[fc.FACE_CLASS[k]] + rng.normal(size=len(fc.FEATURES)) * 0.3))
    return fc.fit_cue(regions, l2=0.1), centres


def test_llr_follows_the_expected_classes_and_abstains_where_none_fits():
    cue, centres = cluster_cue()
    py, my, px = (FACE_NAMES.index(f) for f in ("py", "my", "px"))
    gold, black, end = (centres[fc.CLASS_NAMES.index(c)] for c in ("mli_gold", "mli_black", "end_panel"))
    llr, fits = fc.raw_llr(cue, [(py, gold), (px, end)])  # the pose's +y face looks gold: the pose
    assert llr > 5.0 and fits
    llr, fits = fc.raw_llr(cue, [(py, black), (px, end)])  # it looks black: the half-turn (-y there)
    assert llr < -5.0 and fits
    llr, fits = fc.raw_llr(cue, [(my, black)])  # the pose's -y face looks black: the pose
    assert llr > 5.0 and fits
    llr, fits = fc.raw_llr(cue, [(py, end), (px, end)])  # an end panel where gold or black should be
    assert not fits
    assert fc.raw_llr(cue, []) == (0.0, False)
    clipped = dataclasses.replace(cue, region_clip=1.0)
    assert fc.raw_llr(clipped, [(py, gold), (px, end)])[0] == pytest.approx(1.0)  # +-x regions add nothing


def test_cue_round_trips_through_json():
    cue, _ = cluster_cue()
    cue = dataclasses.replace(cue, temperature=1.7, region_clip=2.0)
    back = fc.FaceCue.from_json(cue.to_json())
    for name in ("mean", "std", "weights", "class_share"):
        np.testing.assert_array_equal(getattr(back, name), getattr(cue, name))
    assert (back.temperature, back.region_clip, back.min_fit) == (1.7, 2.0, cue.min_fit)
    assert fc.FaceCue.from_json(dataclasses.replace(cue, region_clip=np.inf).to_json()).region_clip == np.inf
    assert fc.FaceCue.from_json(None) is None
    with pytest.raises(ValueError, match="features"):
        fc.FaceCue.from_json(cue.to_json().replace('"log_area"', '"area"'))


def naming_pair(p_main, p_alt):
    def one(p, x):
        return Naming(np.full((8, 2), x), np.full((8, 2), x), np.ones(8, bool), np.ones(8, bool), np.arange(8),
                      np.eye(3), np.zeros(3), 1.0, p)
    return dataclasses.replace(one(p_main, 1.0), alternative=one(p_alt, 2.0), ambiguous=p_alt >= 0.1)


def test_weigh_naming_keeps_the_mass_and_swaps_when_the_cue_says_so():
    n = naming_pair(0.6, 0.4)
    assert fc.weigh_naming(n, 0.0, 0.1) is n
    a = fc.weigh_naming(n, np.log(9.0), 0.1)  # odds 1.5 x 9 = 13.5
    assert a.corners_px[0, 0] == 1.0 and a.probability == pytest.approx(13.5 / 14.5)
    assert a.alternative.probability == pytest.approx(1 / 14.5) and not a.ambiguous
    b = fc.weigh_naming(n, -np.log(9.0), 0.1)  # odds 1.5 / 9 = 1/6: the alternative wins
    assert b.corners_px[0, 0] == 2.0 and b.probability == pytest.approx(6 / 7)
    assert b.alternative.corners_px[0, 0] == 1.0 and b.ambiguous  # 1/7 >= 0.1
    assert b.probability + b.alternative.probability == pytest.approx(1.0)


def test_temperature_fit():
    rng = np.random.default_rng(0)
    z = rng.normal(2.0, 2.0, 4000)  # a frame's true log-odds is z; its cue claims 3 z
    truth = rng.random(4000) < 1 / (1 + np.exp(-z))
    llr = np.where(truth, 3 * z, -3 * z)  # the llr of the true pose
    t, _ = fc.fit_temperature(llr)
    assert 2.4 < t < 3.6


def test_calibrate_face_cue_reaches_the_detector(tmp_path):
    """`envisat calibrate --face-cue` on a small generated set (appearance on) writes `face_cue` into the weights'
    metadata; load_detector reads it."""
    import torch

    from envisat_pose.app.cli import main
    from envisat_pose.perception.detect import load_detector
    from envisat_pose.perception.model import CornerNet, ModelConfig
    from envisat_pose.perception.weights import read_metadata, save_weights

    data = tmp_path / "ds"
    assert main(["generate", "--num-images", "100", "--shard-size", "50", "--resolution", "512", "--seed", "21",
                 "--out", str(data), "--quiet"]) == 0
    torch.manual_seed(0)
    w, out = tmp_path / "w.safetensors", tmp_path / "c.safetensors"
    save_weights(str(w), CornerNet(ModelConfig(input_px=64, width=16, depth=2, stem_width=8)))
    assert load_detector(str(w)).face_cue is None
    assert main(["calibrate", "--face-cue", "--weights", str(w), "--data", str(data), "--out", str(out),
                 "--quiet"]) == 0
    meta = read_metadata(str(out))
    record = __import__("json").loads(meta["face_cue_record"])
    assert record["held_out_frames"] == 50 and record["fit_regions"] > 80
    det = load_detector(str(out))
    assert isinstance(det.face_cue, fc.FaceCue) and det.face_cue.temperature > 0


def test_calibrate_face_cue_refuses_other_modes(tmp_path, tiny_dataset, capsys):
    from envisat_pose.app.cli import main

    w = tmp_path / "w.safetensors"
    for extra, msg in ((["--face-cue", "--refine"], "drop --refine"), (["--held-out", tiny_dataset], "--face-cue")):
        assert main(["calibrate", *extra, "--data", tiny_dataset, "--out", str(w), "--quiet"]) == 2
        err = capsys.readouterr().err
        assert msg in err and len(err.strip().splitlines()) == 1, err
    assert not w.exists()
