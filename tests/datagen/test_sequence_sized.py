"""Sequences sized to the target (issue 55, item 4: "sequence scenarios likewise"): a sequence of another target
starts sequence.range_scale (its size against ENVISAT's) times as far as the scenario says, keep-out margin too,
so a 3U CubeSat fills the frame as ENVISAT does instead of showing as a few pixels; ENVISAT's sequences fly the
scenario as written; range_scale = 1 flies the metres; a dataset written before the field reads at 1.

References independent of the code under test: the relative motion's linearity in its start (Clohessy-Wiltshire:
the nonlinear terms are (range / orbit radius)^2 ~ 1e-10 at 50 m), checked on MuJoCo's own simulation at two
starts, and the masks MuJoCo renders for the image share.
"""

import dataclasses
import json
import math

import numpy as np
import pytest

from envisat_pose.config import ConfigError, from_dict
from envisat_pose.datagen.generate_config import GenerateConfig, config_from_json, config_json, nest_moved_keys
from envisat_pose.datagen.scenario import scaled_start, scenario_config
from envisat_pose.datagen.target_scene import size_ratio
from envisat_pose.datagen.truth import simulate_truth
from envisat_pose.datagen.views import sequence_frames
from envisat_pose.state import POS, VEL
from envisat_pose.target import load_target, resolve_target_path

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


def _rod_file(folder) -> str:
    """A 100 m x 6 m x 4 m box (2.8 times ENVISAT's size) with keypoints at its 8 corners."""
    half = (50.0, 3.0, 2.0)
    sites = "".join(f'<site name="kp_{i}" pos="{sx * half[0]} {sy * half[1]} {sz * half[2]}"/>'
                    for i, (sx, sy, sz) in enumerate((x, y, z) for x in (1, -1) for y in (1, -1) for z in (1, -1)))
    path = folder / "rod.xml"
    path.write_text('<mujoco model="rod"><worldbody><body name="target">'
                    '<inertial pos="0 0 0" mass="20000" diaginertia="1.2e5 1.7e7 1.7e7"/>'
                    f'<geom name="rod" type="box" size="{half[0]} {half[1]} {half[2]}"/>{sites}</body></worldbody>'
                    '</mujoco>')
    return str(path)


def _farthest_depth_m(x: np.ndarray, corners_T_m: np.ndarray) -> float:
    """The farthest depth along the boresight (+y of C) of the box's corners over the frames x (N, 12): the
    corners turned into C by the MRP's rotation (Rodrigues' form, written here) and put at the relative position."""
    far = 0.0
    for xk in x:
        p = xk[6:9]
        s = float(p @ p)
        px = np.array([[0, -p[2], p[1]], [p[2], 0, -p[0]], [-p[1], p[0], 0]])
        R_T_from_C = np.eye(3) + (8 * px @ px - 4 * (1 - s) * px) / (1 + s) ** 2  # dcm(p): C -> T
        far = max(far, float((xk[0:3] + corners_T_m @ R_T_from_C)[:, 1].max()))
    return far


def test_a_100m_targets_sequence_sizes_its_depth_scale_from_its_truth(tmp_path):
    """A 100 m box held 140 m off (range_scale 2.807): its far end lies ~160 m deep, beyond the 131 m of 2 mm
    per unit, so a sequence not given depth_scale_m takes the least whole mm whose 16-bit range covers the
    farthest corner of its frames (computed here from the truth and the box), where it was refused before; the
    frames' depth PNGs then hold the box unclipped (no code at 65535, the depths within the box's reach of the
    range). A scale given is kept, one too small still refused; ENVISAT's stays 2 mm."""
    import cv2

    from envisat_pose.app.cli import main
    from envisat_pose.shard_reader import read_shard

    rod = _rod_file(tmp_path)
    cfg = sequence(rod)
    _, x, *_ = sequence_frames(config_json(cfg))
    corners = np.array([(sx * 50.0, sy * 3.0, sz * 2.0) for sx in (1, -1) for sy in (1, -1) for sz in (1, -1)])
    far_m = _farthest_depth_m(x, corners)
    assert far_m > 65535 * 0.002
    assert cfg.depth_scale_m == math.ceil(far_m / 65535 * 1000) / 1000 == 0.003
    assert sequence("models/envisat.xml").depth_scale_m == 0.002
    far = sequence(rod, range_scale=6.0)  # a 300 m hold: ~350 m deep
    far_m = _farthest_depth_m(sequence_frames(config_json(far))[1], corners)
    assert far.depth_scale_m == math.ceil(far_m / 65535 * 1000) / 1000 == 0.006
    # the scale filled in is sized again for a config replaced (it kept 0.003: refused later)
    assert dataclasses.replace(cfg, sequence=far.sequence).depth_scale_m == 0.006
    out = tmp_path / "seq"
    assert main(["generate", "--target", rod, "--mode", "sequence", "--num-images", "2", "--resolution", "64",
                 "--workers", "1", "--out", str(out), "--quiet"]) == 0
    for _, sample in read_shard(str(out / "shard-000000.tar")):
        label = json.loads(sample["json"])
        depth = cv2.imdecode(np.frombuffer(sample["depth.png"], np.uint8), cv2.IMREAD_UNCHANGED)
        fg = depth[depth > 0] * label["depth_scale_m"]
        range_m = float(np.linalg.norm(label["t_cam_from_target_m"]))
        assert label["depth_scale_m"] == 0.003 and depth.max() < 65535 and fg.size > 0
        assert range_m - 50.2 < fg.min() and fg.max() < range_m + 50.2
    given = from_dict(GenerateConfig, {"target": rod, "mode": "sequence", "num_images": 2, "depth_scale_m": 0.01})
    assert given.depth_scale_m == 0.01
    cfg_path = tmp_path / "small.toml"
    cfg_path.write_text('mode = "sequence"\ndepth_scale_m = 0.002\n')
    assert main(["generate", "--config", str(cfg_path), "--target", rod, "--num-images", "2", "--resolution", "64",
                 "--out", str(tmp_path / "refused"), "--quiet"]) == 2
    assert not (tmp_path / "refused").exists()


def test_an_edited_target_file_is_simulated_again_not_read_from_the_cache(tmp_path):
    """sequence_truth is cached for a sequence's frames; the file edited in between (its inertia: another tumble)
    gives the new file's truth, as a fresh process would (the target's other caches key on the file's content)."""
    import os

    from envisat_pose.datagen.truth import sequence_truth

    path = tmp_path / "cs.xml"
    text = open(resolve_target_path(CUBESAT), encoding="utf-8").read()  # the packaged file, from any folder
    old, new = 'fullinertia="0.051115 0.040782 0.016333 0 0 0"', 'fullinertia="0.051115 0.020782 0.036333 0 0 0"'
    assert old in text
    path.write_text(text)
    args = ("default", 0.05, 3, 20.0, 1, str(path))
    before = sequence_truth(*args)[2]
    path.write_text(text.replace(old, new))
    os.utime(path, ns=(os.stat(path).st_atime_ns, os.stat(path).st_mtime_ns + 10**9))  # a later modification
    after = sequence_truth(*args)[2]
    want = simulate_truth(scenario_config("default", duration_s=40.0, dt_s=20.0, seed=1, target={"file": str(path)},
                                          **scaled_start("default", 0.05))).x[:3]
    assert not np.array_equal(before, want)  # the edit changes the truth: the test can tell
    np.testing.assert_array_equal(after, want)
