"""`envisat simulate`: the output contract, determinism, and clear errors for bad input."""

import hashlib
import os
import subprocess
import sys

import numpy as np
import pytest

from envisat_pose.app.cli import main

CONTRACT_KEYS = {"t_s", "x", "chaser_r_m", "chaser_rdot_m_s", "chaser_theta_rad", "chaser_thetadot_rad_s",
                 "corners_C_m", "visible", "corners_px", "in_frame", "config_json"}


def sha256(path):
    return hashlib.sha256(open(path, "rb").read()).hexdigest()


def test_contract_and_plot(tmp_path):
    out = tmp_path / "run.npz"
    assert main(["simulate", "--duration-s", "60", "--dt-s", "2", "--seed", "4", "--out", str(out), "--plot", "--quiet"]) == 0
    with np.load(out, allow_pickle=False) as z:
        assert set(z.files) == CONTRACT_KEYS
        assert z["t_s"].shape == (31,) and z["x"].shape == (31, 12)
        assert z["corners_C_m"].shape == (31, 8, 3) and z["visible"].dtype == bool
        assert '"seed": 4' in str(z["config_json"])
        # corner A relative to the CoM is R_C_from_T v_A, the rotation taken independently from scipy's MRP
        from scipy.spatial.transform import Rotation

        v_A = np.array([5.0, 1.375, 1.0375])  # reference sheet, section 5
        arm = z["corners_C_m"][:, 0] - z["x"][:, 0:3]
        np.testing.assert_allclose(arm, Rotation.from_mrp(z["x"][:, 6:9]).apply(v_A), atol=1e-9)
    assert (tmp_path / "run.png").stat().st_size > 10_000
    assert "seed = 4" in (tmp_path / "run.config.toml").read_text()


def test_same_seed_same_bytes_different_seed_different_attitude(tmp_path):
    paths = []
    for name, seed in (("a", 11), ("b", 11), ("c", 12)):
        paths.append(tmp_path / f"{name}.npz")
        assert main(["simulate", "--duration-s", "30", "--seed", str(seed), "--out", str(paths[-1]), "--quiet"]) == 0
    assert sha256(paths[0]) == sha256(paths[1])
    with np.load(paths[0]) as a, np.load(paths[2]) as c:
        assert np.linalg.norm(a["x"][0, 6:9] - c["x"][0, 6:9]) > 1e-3
        np.testing.assert_array_equal(a["x"][0, 0:6], c["x"][0, 0:6])


BAD_CONFIGS = [
    ("duration_s = -5.0\n", "duration_s", "positive duration"),
    ("dt_s = nan\n", "dt_s", "finite"),
    ("durration_s = 10.0\n", "durration_s", "known key"),
    ("[relative]\nrho0_C_m = [0.0, 3.0, 0.0]\n", "relative.rho0_C_m", "inside the target"),
    ("[orbit]\ne = 1.5\n", "orbit.e", "eccentricity"),
    ("[orbit]\na_m = 6000000.0\n", "orbit.a_m", "Earth"),
    ("[target]\nspin_axis_T = [0.0, 0.0]\n", "target.spin_axis_T", "3 values"),
    ("[target]\nspin_period_s = \"fast\"\n", "target.spin_period_s", "a number"),
    ("seed = -1\n", "seed", "non-negative"),
    ("duration_s = [1\n", "not valid TOML", ""),
    ("max_physics_dt_s = 1e-9\n", "max_physics_dt_s = 1e-09", "physics step"),
    # 15 m along V-bar: the tumbling solar array (reach 22.1 m) sweeps through the chaser (seed 0 at t ~ 455 s)
    ("[relative]\nrho0_C_m = [0.0, 15.0, 0.0]\n", "relative.rho0_C_m", "m from geom 'array'"),
]


@pytest.mark.parametrize("text,field,expected", BAD_CONFIGS)
def test_bad_config_gets_a_clear_message_and_writes_nothing(tmp_path, text, field, expected):
    cfg = tmp_path / "bad.toml"
    cfg.write_text(text)
    out = tmp_path / "run.npz"
    proc = subprocess.run([sys.executable, "-m", "envisat_pose.app.cli", "simulate", "--config", str(cfg), "--out", str(out), "--quiet"],
                          timeout=300,  # a guard: the old code hung on a tiny physics step
                          capture_output=True, text=True)
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert field in proc.stderr and expected in proc.stderr
    assert os.listdir(tmp_path) == ["bad.toml"]


@pytest.mark.parametrize("args,message", [
    (["--duration-s", "-1"], "duration_s = -1.0"),
    (["--dt-s", "0"], "dt_s = 0.0"),
    (["--duration-s", "0.5"], "duration_s = 0.5: expected a duration of at least one output step"),  # not dt_s
    (["--scenario", "nope"], "scenario = 'nope'"),
    (["--config", "/nonexistent/x.toml"], "does not exist"),
    (["--out", "/proc/envisat-test/run.npz"], "cannot write in its folder"),  # a missing folder is made (issue 41)
    (["--out", "run.csv"], "ending in .npz"),
])
def test_bad_arguments(tmp_path, capsys, monkeypatch, args, message):
    monkeypatch.chdir(tmp_path)  # a relative --out lands here, not in the working folder (maybe read-only)
    argv = ["simulate", "--quiet"] + args
    if "--out" not in args:
        argv += ["--out", str(tmp_path / "run.npz")]
    assert main(argv) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "run.npz").exists()


def test_close_25m_scenario_runs(tmp_path):
    """The named close scenario is physically possible: the keep-out check lets it through."""
    out = tmp_path / "close.npz"
    assert main(["simulate", "--scenario", "close-25m", "--duration-s", "300", "--seed", "0", "--out", str(out),
                 "--quiet"]) == 0
    with np.load(out) as z:
        assert abs(np.linalg.norm(z["x"][0, 0:3]) - 25.0) < 1e-9


def test_written_config_reproduces_the_run(tmp_path):
    first = tmp_path / "first.npz"
    assert main(["simulate", "--scenario", "stress-tumble", "--duration-s", "20", "--seed", "9", "--out", str(first), "--quiet"]) == 0
    again = tmp_path / "again.npz"
    written = tmp_path / "first.config.toml"
    assert "`envisat simulate --scenario stress-tumble --config THIS_FILE` remakes it" in written.read_text()
    assert main(["simulate", "--scenario", "stress-tumble", "--config", str(written), "--out", str(again),
                 "--quiet"]) == 0
    assert sha256(first) == sha256(again)  # the scenario's name is recorded in the truth too


def test_the_written_config_alone_reproduces_the_run_and_its_scenario(tmp_path):
    """run.config.toml records the scenario: given back with --config and no --scenario it is the truth's (the
    flag's default, 'default', once overrode it with a warning: the same arrays, but a truth that recorded
    'default', so `estimate --truth` took default's [measurement] table, all markers where the scenario has 3).
    --scenario typed still wins."""
    from envisat_pose.app.cli import build_parser
    from envisat_pose.app.simulate import resolve_config

    first = tmp_path / "first.npz"
    assert main(["simulate", "--scenario", "paper-3markers-0.02", "--duration-s", "5", "--seed", "9", "--out",
                 str(first), "--quiet"]) == 0
    again = tmp_path / "again.npz"
    assert main(["simulate", "--config", str(tmp_path / "first.config.toml"), "--out", str(again), "--quiet"]) == 0
    assert sha256(first) == sha256(again)
    parse = build_parser().parse_args
    written = str(tmp_path / "first.config.toml")
    with pytest.warns(UserWarning, match="is not this job's"):
        assert resolve_config(parse(["simulate", "--config", written, "--scenario", "slow-tumble"])
                              ).scenario == "slow-tumble"
    assert resolve_config(parse(["simulate"])).scenario == "default"


def test_an_interrupt_inside_an_import_is_reported_as_an_interrupt(monkeypatch, tmp_path, capsys):
    """Ctrl-C landing inside a module's import: the cleanup's own import of that half-loaded module fails with an
    ImportError whose context is the KeyboardInterrupt; the verb says it was interrupted (exit 130), no traceback.
    Any other error still propagates."""
    import envisat_pose.app.simulate as verb
    from envisat_pose.app.cli import main

    def interrupted_import(args):
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt:
            raise ImportError("cannot import name 'x' from partially initialized module 'mujoco'") from None

    monkeypatch.setattr(verb, "run_simulate_cli", interrupted_import)
    assert main(["simulate", "--out", str(tmp_path / "r.npz")]) == 130
    assert capsys.readouterr().err.strip() == "envisat simulate: interrupted"

    def plain_bug(args):
        raise ImportError("a real one")

    monkeypatch.setattr(verb, "run_simulate_cli", plain_bug)
    with pytest.raises(ImportError, match="a real one"):
        main(["simulate", "--out", str(tmp_path / "r.npz")])


BIG_BOX = """<mujoco model="bigbox"><worldbody><body name="target">
<geom type="box" size="50 3 2" mass="20000"/>
<site name="kp_a" pos="50 3 2"/><site name="kp_b" pos="-50 3 2"/><site name="kp_c" pos="50 -3 -2"/>
<site name="kp_d" pos="-50 -3 -2"/><site name="kp_e" pos="0 3 -2"/>
</body></worldbody></mujoco>
"""


def test_a_target_larger_than_the_hold_is_told_the_start_that_clears_it(tmp_path, capsys):
    """A 100 m box at the default scenario's 50 m hold: one line that gives the scaled start (as `run` and
    `generate --mode sequence` fly it), and that start, written into a config file as the line says, simulates."""
    import json
    import re

    target = tmp_path / "big.xml"
    target.write_text(BIG_BOX)
    out = tmp_path / "run.npz"
    args = ["simulate", "--target", str(target), "--duration-s", "10", "--out", str(out), "--quiet"]
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "inside the target" in err[0] and not out.exists(), err
    rho0, rhodot0 = re.search(r"rho0_C_m = (\[[^\]]*\]), rhodot0_C_m_s = (\[[^\]]*\])", err[0]).groups()
    assert np.linalg.norm(json.loads(rho0)) > np.linalg.norm([50, 3, 2])  # outside the box's corners
    cfg = tmp_path / "far.toml"
    cfg.write_text(f"[relative]\nrho0_C_m = {rho0}\nrhodot0_C_m_s = {rhodot0}\n")
    assert main([*args, "--config", str(cfg)]) == 0 and out.exists()


def test_a_start_inside_a_small_target_is_not_told_a_scaled_start_that_comes_nearer(tmp_path, capsys):
    """A 3U CubeSat (0.036 times ENVISAT's size) with a start inside it: the scaled start would be nearer still (and
    inside), so the line gives the radius and no 'start it farther' start (it gave [0, 0.005467, 0] m)."""
    cfg = tmp_path / "near.toml"
    cfg.write_text("[relative]\nrho0_C_m = [0.0, 0.15, 0.0]\n")
    out = tmp_path / "run.npz"
    args = ["simulate", "--target", "models/cubesat_3u.xml", "--config", str(cfg), "--duration-s", "10",
            "--out", str(out), "--quiet"]
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "inside the target" in err[0] and not out.exists(), err
    assert "farther" not in err[0] and "0.005467" not in err[0], err


def test_the_written_config_records_the_target_files_sha256_and_a_rerun_refuses_the_file_changed(tmp_path, capsys):
    """run.config.toml records its target file's sha256 as run.npz does ([target] sha256): a rerun from it while
    the file is as it was makes the same truth; once the file changed it is refused in one line naming it and both
    sha256 (nothing written), as `estimate --truth` refuses such a truth; another file given over it simulates."""
    import json
    import shutil
    import tomllib

    from envisat_pose.target import resolve_target_path

    target = tmp_path / "stage.xml"
    shutil.copy(resolve_target_path("models/upper_stage.xml"), target)
    first, again, edited = tmp_path / "first.npz", tmp_path / "again.npz", tmp_path / "edited.npz"
    assert main(["simulate", "--target", str(target), "--duration-s", "5", "--out", str(first), "--quiet"]) == 0
    written = tmp_path / "first.config.toml"
    with np.load(first) as z:
        recorded = json.loads(str(z["config_json"]))["target"]["sha256"]
    assert tomllib.loads(written.read_text())["target"]["sha256"] == recorded
    assert main(["simulate", "--config", str(written), "--out", str(again), "--quiet"]) == 0
    assert sha256(first) == sha256(again)
    target.write_text(target.read_text() + "<!-- edited since -->\n")
    capsys.readouterr()
    assert main(["simulate", "--config", str(written), "--out", str(edited), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "changed since the config was written" in err[0] and str(target) in err[0], err
    assert recorded[:12] in err[0] and not edited.exists(), err
    assert main(["simulate", "--config", str(written), "--target", "models/upper_stage.xml", "--out", str(edited),
                 "--quiet"]) == 0
