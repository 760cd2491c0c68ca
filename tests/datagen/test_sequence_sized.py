"""Sequences sized to the target (issue 55, item 4: "sequence scenarios likewise"): a sequence of another target
starts sequence.range_scale (its size against ENVISAT's) times as far as the scenario says, keep-out margin too,
so a 3U CubeSat fills the frame as ENVISAT does instead of showing as a few pixels; ENVISAT's sequences fly the
scenario as written; range_scale = 1 flies the metres; a dataset written before the field reads at 1.

References independent of the code under test: the relative motion's linearity in its start (Clohessy-Wiltshire:
the nonlinear terms are (range / orbit radius)^2 ~ 1e-10 at 50 m), checked on MuJoCo's own simulation at two
starts, and the masks MuJoCo renders for the image share.
"""

import numpy as np
import pytest

from envisat_pose.config import ConfigError, from_dict
from envisat_pose.datagen.generate_config import GenerateConfig, config_from_json, config_json, nest_moved_keys
from envisat_pose.datagen.scenario import scaled_start, scenario_config
from envisat_pose.datagen.target_scene import size_ratio
from envisat_pose.datagen.truth import simulate_truth
from envisat_pose.datagen.views import sequence_frames
from envisat_pose.state import POS, VEL
from envisat_pose.target import load_target

CUBESAT = "models/cubesat_3u.xml"
UPPER_STAGE = "models/upper_stage.xml"


def sequence(target: str, **sequence_table) -> GenerateConfig:
    return from_dict(GenerateConfig, {"target": target, "mode": "sequence", "num_images": 31, "resolution_px": 128,
                                      "sequence": {"scenario": "default", **sequence_table}})


def test_envisats_sequence_flies_the_scenario_as_written():
    """range_scale 1 exactly, no override, and the frames' truth that of the scenario itself (same run)."""
    cfg = sequence("models/envisat.xml")
    assert cfg.sequence.range_scale == 1.0 and scaled_start("default", 1.0) == {}
    _, x, *_ = sequence_frames(config_json(cfg))
    plain = simulate_truth(scenario_config("default", duration_s=30.0, dt_s=1.0, seed=cfg.seed))
    np.testing.assert_array_equal(x, plain.x)


@pytest.mark.parametrize("target", [CUBESAT, UPPER_STAGE])
def test_another_targets_sequence_starts_sized_and_moves_as_the_scenario_scaled(target):
    """range_scale = size_ratio to 4 digits; the start range 50 m x range_scale; the whole relative trajectory
    that of the scenario's metres times range_scale, to the second-order gravity term the linear model leaves out
    (at most 3 n^2 rho^2 / r in acceleration, twice the Taylor term's 3/2, over the 30 s), the target's tumble
    the same; the keep-out margin scaled."""
    cfg = sequence(target)
    scale = cfg.sequence.range_scale
    assert scale == pytest.approx(size_ratio(load_target(target)), rel=1e-3) and scale < 1.0
    _, x, *_ = sequence_frames(config_json(cfg))
    assert np.linalg.norm(x[0, POS]) == pytest.approx(50.0 * scale, rel=1e-12)
    metres = simulate_truth(scenario_config("default", duration_s=30.0, dt_s=1.0, seed=cfg.seed,
                                            target={"file": target}))
    orbit = scenario_config("default").orbit
    accel_m_s2 = 3.0 * orbit.n_rad_s**2 * 50.0**2 / (orbit.a_m * (1.0 - orbit.e))
    np.testing.assert_allclose(x[:, POS], scale * metres.x[:, POS], rtol=0, atol=accel_m_s2 * 30.0**2 / 2)
    np.testing.assert_allclose(x[:, VEL], scale * metres.x[:, VEL], rtol=0, atol=accel_m_s2 * 30.0)
    assert accel_m_s2 * 30.0**2 / 2 < 1e-6 * 50.0 * scale  # the bound is tight: a micron-scale of the range
    np.testing.assert_allclose(x[:, 6:], metres.x[:, 6:], rtol=0, atol=1e-9)
    assert scaled_start("default", scale)["keepout_margin_m"] == pytest.approx(2.0 * scale, rel=1e-12)


def test_a_sized_cubesat_fills_the_frame_as_envisat_does(tmp_path):
    """The first frame's mask (MuJoCo's render, 128 px): the sized CubeSat covers within a factor 2 of ENVISAT's
    share (6 % each at 256 px, seed 0; at the scenario's 50 m it spans under 4 px and the sequence is refused:
    test_views_sized)."""
    import cv2

    from envisat_pose.app.cli import main
    from envisat_pose.shard_reader import read_shard

    share = {}
    for name, target in (("envisat", "models/envisat.xml"), ("cubesat", CUBESAT)):
        out = tmp_path / name
        assert main(["generate", "--target", target, "--mode", "sequence", "--num-images", "1", "--resolution",
                     "128", "--workers", "1", "--out", str(out), "--quiet"]) == 0
        _, sample = next(read_shard(str(out / "shard-000000.tar")))
        mask = cv2.imdecode(np.frombuffer(sample["mask.png"], np.uint8), cv2.IMREAD_UNCHANGED)
        share[name] = float((mask > 0).mean())
    assert 0.01 < share["envisat"] and 0.5 < share["cubesat"] / share["envisat"] < 2.0, share


def test_range_scale_given_is_kept_and_checked():
    """1 flies the scenario's 50 m for another target; a non-positive or absurd factor is one named error."""
    cfg = from_dict(GenerateConfig, {"target": UPPER_STAGE, "mode": "sequence", "num_images": 2,
                                     "resolution_px": 256, "sequence": {"range_scale": 1.0}})
    _, x, *_ = sequence_frames(config_json(cfg))
    assert np.linalg.norm(x[0, POS]) == pytest.approx(50.0, rel=1e-12)
    for bad in (0.0, -1.0, 100.0):
        with pytest.raises(ConfigError, match="sequence.range_scale"):
            sequence(UPPER_STAGE, range_scale=bad)


def test_a_sequence_stored_before_range_scale_reads_at_its_metres():
    """A manifest's config written before the field (a CubeSat sequence then flew 50 m) reads at 1; a random-mode
    config is left as it was; today's configs travel to the workers unchanged."""
    old = {"mode": "sequence", "target": CUBESAT, "resolution_px": 1024, "sequence": {"scenario": "default"}}
    assert nest_moved_keys(old)["sequence"]["range_scale"] == 1.0
    assert "range_scale" not in nest_moved_keys({"mode": "random"}).get("sequence", {})
    cfg = sequence(CUBESAT)
    assert config_from_json(config_json(cfg)) == cfg
