"""The shipped detector weights (models/detector.safetensors) on a small set freshly generated here with a seed no
training or calibration set used: full 1024 px frames, appearance randomization and the space camera on.

The floors are the measured performance of these weights on 200 held-out random views (seeds 8181 and 9191, 100
frames each, default generate config; the model card's evaluations and bench/results/detector_floors.json)
less a margin for a 24-frame sample (binomial standard error of a share p over ~140 corners:
sqrt(p (1 - p) / 140) ~ 3-4 points; 3 standard errors). They guard against a regression of the weights or of
the detection chain; they are not issue 26's floors (PCK@5 >= 95 %, named wrongly <= 1.5 %, visibility >= 96 %),
which these weights do not reach yet (the README's detector section says which need more GPU time).
"""

import json
import os

import numpy as np
import pytest

from envisat_pose.perception.data import shard_paths
from envisat_pose.perception.detect import load_detector
from envisat_pose.perception.evaluate import score_method
from envisat_pose.perception.weights import shipped_weights_path
from envisat_pose.pipelines.detector.detect import camera_samples

FRAMES = 24
SEED = 8_675_309  # not a seed of the card's training (101, 111), calibration (303) or evaluation (404, 505) sets


@pytest.fixture(scope="module")
def fresh_set(tmp_path_factory):
    from envisat_pose.app.cli import main

    out = tmp_path_factory.mktemp("shipped") / "ds"
    assert main(["generate", "--num-images", str(FRAMES), "--shard-size", "12", "--seed", str(SEED),
                 "--out", str(out), "--quiet"]) == 0
    return str(out)


@pytest.fixture(scope="module")
def scored(fresh_set):
    import torch

    torch.set_num_threads(2)
    det = load_detector(shipped_weights_path())
    rows = {k: [] for k in ("pred", "alt", "amb", "vis", "cov", "true", "use")}
    for _key, image, label in camera_samples(shard_paths(fresh_set)):
        f = det.detect(image, label["K"])
        for k, v in (("pred", f.corners_px), ("alt", f.alt_corners_px), ("amb", f.ambiguous), ("vis", f.visible),
                     ("cov", f.cov_px), ("true", label["corners_px"]), ("use", label["visible"] & label["in_frame"])):
            rows[k].append(v)
    a = {k: np.array(v) for k, v in rows.items()}
    s = score_method(a["pred"], a["true"], a["use"], alt_px=a["alt"], ambiguous=a["amb"], pred_visible=a["vis"],
                     cov_px=a["cov"])
    print(json.dumps({k: s[k] for k in ("pck_2px", "pck_5px", "swap_rate_strict", "ambiguous_share")}),
          s["errors"]["all"], s["visibility"], s["calibration"])
    return s


def test_the_card_lies_beside_the_weights():
    path = shipped_weights_path()
    card = json.load(open(os.path.join(os.path.dirname(path), "detector.json"), encoding="utf-8"))
    assert os.path.getsize(path) < 20 * 2 ** 20
    from envisat_pose.io import sha256_file

    assert card["weights"]["sha256"] == sha256_file(path)
    # every leg by its command and git hash: `envisat train`, or a harness over the project's pipeline (the GPU legs)
    assert card["training_runs"] and all(r["command"].startswith("envisat train") or r.get("harness")
                                         for r in card["training_runs"])
    assert all(r["git"] for r in card["training_runs"])


def test_localization_and_naming(scored):
    assert scored["usable_corners"] >= 100
    assert scored["errors"]["all"]["median_px"] <= FLOORS["median_px"]
    assert scored["pck_5px"] >= FLOORS["pck_5px"]
    assert scored["pck_2px"] >= FLOORS["pck_2px"]
    assert scored["swap_rate_strict"] <= FLOORS["swap_rate_strict"]
    assert scored["ambiguous_share"] <= FLOORS["ambiguous_share"]


def test_visibility(scored):
    assert scored["visibility"]["precision"] >= FLOORS["vis_precision"]
    assert scored["visibility"]["recall"] >= FLOORS["vis_recall"]


def test_calibrated_covariance(scored):
    """The shipped cov_scale keeps the mean e^T C^-1 e of correctly named corners near 2 (the issue's band
    [1.6, 2.6], widened for the sample)."""
    assert scored["calibration"]["count"] >= 50
    assert FLOORS["nees_low"] <= scored["calibration"]["mean_nees"] <= FLOORS["nees_high"]


# measured with envisat evaluate on 200 held-out random views (seeds 8181 and 9191, 1221 usable corners; the
# detector as this test runs it, with the patch pass): median 0.52 and 0.50 px, PCK@2 75.6 %, PCK@5 81.0 %,
# strict swaps 6.0 %, half-turn ambiguous 3.5 % of frames, visibility precision 95.3 % and recall 88.9 %, mean
# NEES 2.01 and 1.79; less the margin in the module doc (the ambiguous share over 24 frames: 3 x 3.8 points). On
# this test's own 24 frames (seed 8675309) they measured median 0.44 px, PCK@2 79.6 %, PCK@5 83.2 %, swaps
# 7.6 %, ambiguous 8.3 %, visibility 93.2 / 89.8 %, mean NEES 1.85 (the weights before, 60ada03's tensors:
# PCK@5 73.0 %, swaps 4.2 %, ambiguous 29 %, recall 80.3 %).
FLOORS = {"median_px": 0.9, "pck_5px": 0.71, "pck_2px": 0.64, "swap_rate_strict": 0.12, "ambiguous_share": 0.15,
          "vis_precision": 0.90, "vis_recall": 0.81, "nees_low": 1.2, "nees_high": 3.2}
