"""`envisat estimate`: the est.npz contract, determinism, --truth and --scenario, and one-line user errors."""

import gc
import json
import os
import warnings

import numpy as np
import pytest

from envisat_pose.app.cli import main
from envisat_pose.filtering.estimator import FilterConfig

KEYS = {"t_s", "x_true", "x_hat", "P", "n_meas", "nis", "nis_dof", "diverged", "judged", "config_json"}


def _load(path):
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def test_scenario_run_writes_the_contract_and_is_deterministic(tmp_path, capsys):
    args = ["estimate", "--scenario", "default", "--duration-s", "120", "--runs", "3", "--seed", "4", "--quiet"]
    assert main(args + ["--out", str(tmp_path / "a.npz")]) == 0
    assert main(args + ["--out", str(tmp_path / "b.npz")]) == 0
    assert (tmp_path / "a.npz").read_bytes() == (tmp_path / "b.npz").read_bytes()
    assert (tmp_path / "a.config.toml").exists()
    est = _load(tmp_path / "a.npz")
    assert set(est) == KEYS
    R, T = 3, 121
    assert est["t_s"].shape == (T,)
    assert est["x_true"].shape == est["x_hat"].shape == (R, T, 12)
    assert est["P"].shape == (R, T, 12, 12)
    assert est["n_meas"].shape == est["nis"].shape == (R, T)
    assert est["diverged"].shape == (R,) and est["diverged"].dtype == bool and not est["diverged"].any()
    cfg = json.loads(str(est["config_json"]))
    assert cfg["estimate"]["runs"] == 3 and cfg["truth_source"] == {"scenario": "default"}
    assert cfg["truth_config"]["duration_s"] == 120.0
    # runs differ (their own initial errors and noise), and converge on the truth
    assert np.abs(est["x_hat"][0, 0] - est["x_hat"][1, 0]).max() > 1e-3
    assert np.abs(est["x_hat"][:, -1, :3] - est["x_true"][:, -1, :3]).max() < 0.05
    out = capsys.readouterr().out
    assert "RMS attitude error" in out and "deg" in out
    assert main(args[:-3] + ["--seed", "5", "--quiet", "--out", str(tmp_path / "c.npz")]) == 0
    assert (tmp_path / "c.npz").read_bytes() != (tmp_path / "a.npz").read_bytes()


def test_truth_file_and_rate(tmp_path):
    from envisat_pose.datagen.scenario import scenario_config
    from envisat_pose.datagen.truth import simulate_truth

    tr = simulate_truth(scenario_config("default", duration_s=200.0, seed=3))
    tr.save(str(tmp_path / "run.npz"))
    out = tmp_path / "est.npz"
    assert main(["estimate", "--truth", str(tmp_path / "run.npz"), "--rate-hz", "0.5", "--runs", "2",
                 "--measurements", "pixels", "--sigma-px", "0.5", "--max-markers", "4", "--quiet",
                 "--out", str(out)]) == 0
    est = _load(out)
    np.testing.assert_array_equal(est["t_s"], tr.t_s[::2])
    np.testing.assert_array_equal(est["x_true"][1], tr.x[::2])
    assert est["n_meas"].max() == 4 and est["n_meas"].min() >= 1
    assert json.loads(str(est["config_json"]))["estimate"]["measurement"]["kind"] == "pixels"


@pytest.mark.parametrize("extra, needle", [
    (["--scenario", "default", "--sigma-m", "-1"], "--sigma-m -1.0: expected a positive noise sigma"),
    (["--scenario", "default", "--rate-hz", "0.3", "--duration-s", "10"], "rate_hz"),
    (["--scenario", "no_such"], "scenario"),
    (["--truth", "/nonexistent/run.npz"], "no such file"),
    (["--scenario", "default", "--runs", "0"], "runs"),
    (["--scenario", "default", "--out", "est.txt"], ".npz"),
])
def test_user_errors_are_one_line(tmp_path, capsys, monkeypatch, extra, needle):
    monkeypatch.chdir(tmp_path)  # a relative --out lands here, not in the working folder (maybe read-only)
    args = ["estimate", "--quiet"] + extra
    if "--out" not in extra:
        args += ["--out", str(tmp_path / "e.npz")]
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and needle in err and "Traceback" not in err
    assert not (tmp_path / "e.npz").exists()


@pytest.mark.parametrize("verb", ["estimate", "montecarlo"])
def test_a_noise_flag_of_another_measurement_is_refused(tmp_path, capsys, verb):
    """--sigma-px on 3D markers changed nothing (the same bytes out): refused in one line, nothing written; the
    pixel noise of the pixels scenario is taken."""
    out = str(tmp_path / ("e.npz" if verb == "estimate" else "mc"))
    base = [verb, "--duration-s", "10", "--runs", "2", "--out", out, "--quiet"]
    assert main(base + ["--scenario", "default", "--sigma-px", "5"]) == 2
    err = capsys.readouterr().err
    assert "--sigma-px: the noise of pixels or pixels+range measurements; this job measures markers3d" in err, err
    assert main(base + ["--scenario", "default", "--measurements", "pixels", "--sigma-m", "0.1"]) == 2
    assert "--sigma-m: the noise of markers3d measurements; this job measures pixels" in capsys.readouterr().err
    assert not os.path.exists(out)
    if verb == "estimate":
        assert main(base + ["--scenario", "pixels-1px", "--sigma-px", "2"]) == 0


def test_config_file_then_flags(tmp_path):
    cfg = tmp_path / "est.toml"
    cfg.write_text('runs = 2\n[measurement]\nsigma_m = 0.05\nfailure_prob = 0.2\noutages_s = [[20.0, 40.0]]\n'
                   '[filter]\nadaptive_q = true\n')
    out = tmp_path / "est.npz"
    assert main(["estimate", "--scenario", "default", "--duration-s", "60", "--config", str(cfg), "--sigma-m", "0.03",
                 "--quiet", "--out", str(out)]) == 0
    est = _load(out)
    c = json.loads(str(est["config_json"]))["estimate"]
    assert c["runs"] == 2 and c["measurement"]["sigma_m"] == 0.03 and c["filter"]["adaptive_q"] is True
    assert c["measurement"]["failure_prob"] == 0.2
    assert (est["n_meas"][:, 20:40] == 0).all() and (est["n_meas"][:, :20] > 0).any()
    assert np.isfinite(est["x_hat"]).all()
    # the written config reproduces the job
    out2 = tmp_path / "again.npz"
    assert main(["estimate", "--scenario", "default", "--duration-s", "60", "--config",
                 str(tmp_path / "est.config.toml"), "--quiet", "--out", str(out2)]) == 0
    assert out2.read_bytes() == out.read_bytes()


def test_the_written_config_names_the_truth_it_filtered(tmp_path):
    """est.config.toml's fields hold no truth: its header names the scenario simulated and for how long (a 30 s
    job given back with only --scenario and --config simulated the scenario's 1800 s), or the truth file and its
    sha256, each with the command that remakes the job; that command remakes it to the byte."""
    import hashlib
    import shlex

    out = tmp_path / "est.npz"
    assert main(["estimate", "--scenario", "slow-tumble", "--duration-s", "30", "--runs", "2", "--seed", "4",
                 "--quiet", "--out", str(out)]) == 0
    header = next(line for line in (tmp_path / "est.config.toml").read_text().splitlines()
                  if line.startswith("# truth:"))
    assert header.startswith("# truth: scenario 'slow-tumble' simulated for 30 s"), header
    command = shlex.split(header.split("`")[1].replace("THIS_FILE", str(tmp_path / "est.config.toml")))
    again = tmp_path / "again.npz"
    assert main(command[1:] + ["--quiet", "--out", str(again)]) == 0
    assert again.read_bytes() == out.read_bytes()
    truth = tmp_path / "run.npz"
    assert main(["simulate", "--duration-s", "10", "--out", str(truth), "--quiet"]) == 0
    assert main(["estimate", "--truth", str(truth), "--quiet", "--out", str(tmp_path / "t" / "est.npz")]) == 0
    sha = hashlib.sha256(truth.read_bytes()).hexdigest()
    assert f"# truth: {truth} (sha256 {sha}); `envisat estimate --truth {truth} --config THIS_FILE`" in (
        tmp_path / "t" / "est.config.toml").read_text()


def test_a_bad_value_is_named_where_the_user_wrote_it(tmp_path, capsys):
    """The flag typed, or the config file's field (the same error, the same field: the value's own source)."""
    cfg = tmp_path / "bad.toml"
    cfg.write_text("[measurement]\nsigma_m = -2.0\n")
    for extra, line in ((["--config", str(cfg)], "measurement.sigma_m = -2.0: expected a positive noise sigma"),
                        (["--config", str(cfg), "--sigma-m=-3"], "--sigma-m -3.0: expected a positive noise sigma")):
        assert main(["estimate", "--scenario", "default", "--out", str(tmp_path / "e.npz"), "--quiet"] + extra) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith(f"envisat estimate: error: {line}") and "\n" not in err, (extra, err)
    assert not (tmp_path / "e.npz").exists()


def test_config_file_unknown_key_is_a_one_line_error(tmp_path, capsys):
    cfg = tmp_path / "bad.toml"
    cfg.write_text("[filter]\nalpha_typo = 1.0\n")
    assert main(["estimate", "--scenario", "default", "--config", str(cfg), "--out", str(tmp_path / "e.npz")]) == 2
    err = capsys.readouterr().err
    assert "filter.alpha_typo" in err and len(err.strip().splitlines()) == 1


@pytest.fixture(scope="module")
def truth_file(tmp_path_factory):
    """A 60 s MuJoCo truth of the default scenario, saved as run.npz."""
    from envisat_pose.datagen.scenario import scenario_config
    from envisat_pose.datagen.truth import simulate_truth

    path = tmp_path_factory.mktemp("truth") / "run.npz"
    simulate_truth(scenario_config("default", duration_s=60.0, seed=2)).save(str(path))
    return path


def test_a_rate_off_the_truths_grid_makes_no_folder(truth_file, tmp_path, capsys):
    """A truth file at 1 s and a 0.3 Hz filter: refused in one line before anything is made (the output's folder
    was once created first, then left empty)."""
    out = tmp_path / "new" / "est.npz"
    assert main(["estimate", "--truth", str(truth_file), "--rate-hz", "0.3", "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "whole multiple of the truth's sample step 1 s" in err
    assert not (tmp_path / "new").exists()


def test_runs_that_never_measure_are_said_to(tmp_path, capsys):
    """An R-bar start (the target 50 m above the chaser, out of the camera's view along the V-bar) measured in
    pixels: no step of any run has a measurement, and the verb warns that its figures are the prior's."""
    from envisat_pose.config import from_dict
    from envisat_pose.datagen.scenario import ScenarioConfig
    from envisat_pose.datagen.truth import simulate_truth

    truth = tmp_path / "rbar.npz"
    simulate_truth(from_dict(ScenarioConfig, {"duration_s": 20.0, "relative": {"rho0_C_m": [50.0, 0.0, 0.0]}}
                             )).save(str(truth))
    out = tmp_path / "est.npz"
    assert main(["estimate", "--truth", str(truth), "--measurements", "pixels", "--runs", "2", "--out", str(out),
                 "--quiet"]) == 0
    assert not _load(out)["n_meas"].any()
    assert "warning: no step of any run had a measurement" in capsys.readouterr().err


def test_runs_whose_every_update_fails_are_not_said_to_miss_the_target(tmp_path, capsys):
    """The target in view at every step but a noise sigma of 1e-9 m against P0's 1 m: every update fails (its
    innovation covariance not positive definite) and is rolled back. The warning says the truth offered keypoints
    and the updates failed, not that the target was never in view (as it once did); the campaign's likewise."""
    from envisat_pose.config import from_dict
    from envisat_pose.datagen.scenario import ScenarioConfig
    from envisat_pose.datagen.truth import simulate_truth

    truth = tmp_path / "vbar.npz"
    simulate_truth(from_dict(ScenarioConfig, {"duration_s": 10.0})).save(str(truth))
    out = tmp_path / "est.npz"
    assert main(["estimate", "--truth", str(truth), "--sigma-m", "1e-9", "--runs", "2", "--out", str(out),
                 "--quiet"]) == 0
    assert not _load(out)["n_meas"].any()
    err = capsys.readouterr().err
    assert "although the truth offered keypoints" in err and "never in view" not in err, err
    assert main(["montecarlo", "--scenario", "default", "--duration-s", "10", "--sigma-m", "1e-9", "--runs", "2",
                 "--out", str(tmp_path / "mc"), "--quiet"]) == 0
    err = capsys.readouterr().err
    assert "although the truth offered keypoints" in err and "never in view" not in err, err


def test_a_fast_tumble_is_filtered_consistently(tmp_path):
    """An 8 s tumble (45 deg/s) at the filter's 1 Hz: its RK4 sub-steps follow the estimated rate, so the filter
    stays consistent (mean NEES 3337 and every run diverged when it stepped 1 s whatever the rate)."""
    from envisat_pose.config import from_dict
    from envisat_pose.datagen.scenario import ScenarioConfig
    from envisat_pose.datagen.truth import simulate_truth

    truth = tmp_path / "fast.npz"
    simulate_truth(from_dict(ScenarioConfig, {"duration_s": 120.0, "target": {"spin_period_s": 8.0}})).save(str(truth))
    out = tmp_path / "est.npz"
    assert main(["estimate", "--truth", str(truth), "--runs", "5", "--seed", "3", "--out", str(out), "--quiet"]) == 0
    est = _load(out)
    from envisat_pose.filtering.estimator import nees

    assert not est["diverged"].any()
    assert 6.0 < float(nees(est["x_true"], est["x_hat"], est["P"])[:, 60:].mean()) < 18.0


def test_estimate_from_a_truth_file_does_not_import_mujoco(truth_file, tmp_path):
    """`estimate --truth` reads the core's contract: neither MuJoCo nor the simulator (datagen.sim, datagen.truth)
    is imported. (The parser of `envisat simulate` imports datagen.scenario, which is plain Python.)"""
    import subprocess
    import sys

    code = ("import sys; from envisat_pose.app.cli import main; "
            f"rc = main(['estimate', '--truth', {str(truth_file)!r}, '--runs', '2', '--quiet', "
            f"'--measurements', 'pixels', '--out', {str(tmp_path / 'est.npz')!r}]); "
            "print('RC', rc, sorted(m for m in sys.modules if m.split('.')[0] == 'mujoco' "
            "or m in ('envisat_pose.datagen.sim', 'envisat_pose.datagen.truth')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert "RC 0 []" in out.stdout, out.stdout
    from envisat_pose.contracts import Estimates

    est = Estimates.load(str(tmp_path / "est.npz"))
    assert est.x_hat.shape == (2, 61, 12) and not est.diverged.any()


def _contract_valid_truth_without_orbit(truth_file, path):
    from envisat_pose.contracts import TruthTrajectory

    tr = TruthTrajectory.load(str(truth_file))
    tr.config_json = json.dumps({"target": {"gravity_gradient": False}})
    tr.save(str(path))


@pytest.mark.parametrize("how", ["truncated", "random_bytes", "estimates_file", "empty", "config_without_orbit",
                                 "text"])
def test_a_corrupt_truth_file_is_one_error_line(truth_file, tmp_path, capsys, how):
    bad = tmp_path / "bad.npz"
    data = truth_file.read_bytes()
    if how == "truncated":
        bad.write_bytes(data[: len(data) // 2])
    elif how == "random_bytes":
        bad.write_bytes(np.random.default_rng(0).integers(0, 256, 4096, dtype=np.uint8).tobytes())
    elif how == "estimates_file":
        assert main(["estimate", "--truth", str(truth_file), "--quiet", "--out", str(bad)]) == 0
        capsys.readouterr()
    elif how == "empty":
        bad.write_bytes(b"")
    elif how == "text":  # once read as a pickle by numpy, whose line then offered to load it unsafely
        bad.write_text("hello\n")
    else:
        _contract_valid_truth_without_orbit(truth_file, bad)
    out = tmp_path / "e.npz"
    gc.collect()  # what earlier tests left unclosed is theirs: collected before, not counted here
    with warnings.catch_warnings(record=True) as seen:  # numpy's np.load leaves its file open on a damaged zip
        warnings.simplefilter("always")
        assert main(["estimate", "--truth", str(bad), "--quiet", "--out", str(out)]) == 2
        gc.collect()
    assert not [w for w in seen if issubclass(w.category, ResourceWarning) and "bad.npz" in str(w.message)]
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err and "bad.npz" in err, err
    assert "pickle" not in err
    assert not out.exists()


def test_the_filter_takes_mu_from_the_truth(tmp_path):
    """A truth on a world with mu 20 % larger (still a valid orbit): the estimate uses the truth's mu and stays
    consistent (a filter with the Earth's mu would diverge in every run, mean NEES ~4e4)."""
    from envisat_pose.datagen.scenario import scenario_config
    from envisat_pose.datagen.truth import simulate_truth
    from envisat_pose.filtering.estimator import nees

    mu = 1.2 * 3.986004418e14
    tr = simulate_truth(scenario_config("default", duration_s=300.0, seed=3, orbit={"mu_m3_s2": mu}))
    tr.save(str(tmp_path / "run.npz"))
    out = tmp_path / "est.npz"
    assert main(["estimate", "--truth", str(tmp_path / "run.npz"), "--runs", "20", "--seed", "1", "--quiet",
                 "--out", str(out)]) == 0
    est = _load(out)
    assert json.loads(str(est["config_json"]))["truth_config"]["orbit"]["mu_m3_s2"] == mu
    anees = nees(est["x_true"], est["x_hat"], est["P"]).mean()
    print(f"mu x 1.2: mean NEES {anees:.2f}")
    assert not est["diverged"].any() and 6.0 < anees < 24.0


def test_the_filter_takes_the_gravity_gradient_switch_from_the_truth(tmp_path):
    """The gravity-gradient scenario: the truth's config switches the model's torque on, so no run diverges
    (torque-free with the default Q, every run would)."""
    out = tmp_path / "est.npz"
    assert main(["estimate", "--scenario", "gravity-gradient", "--duration-s", "300", "--runs", "10", "--seed", "2",
                 "--quiet", "--out", str(out)]) == 0
    est = _load(out)
    assert json.loads(str(est["config_json"]))["truth_config"]["target"]["gravity_gradient"] is True
    assert not est["diverged"].any()


def test_the_pipeline_writes_what_the_verb_writes(truth_file, tmp_path, capsys):
    """The verb is an argument parser over pipelines.estimate: run_estimate with the config the flags resolve to
    writes the same est.npz and config; a truth file keeps the configured outages (no scenario, no eclipse)."""
    from envisat_pose.app.cli import build_parser
    from envisat_pose.app.estimate import resolve_config
    from envisat_pose.pipelines.campaigns.estimate import run_estimate

    args = ["estimate", "--truth", str(truth_file), "--runs", "2", "--outage", "10", "20", "--quiet"]
    assert main(args + ["--out", str(tmp_path / "cli.npz")]) == 0
    assert "wrote" in capsys.readouterr().out
    cfg = resolve_config(build_parser().parse_args(args + ["--out", "unused.npz"]))
    res = run_estimate(cfg, str(tmp_path / "api.npz"), truth_path=str(truth_file))
    assert res["config"] == cfg and res["plot"] is None and res["rrd"] is None
    assert (tmp_path / "api.npz").read_bytes() == (tmp_path / "cli.npz").read_bytes()
    assert (tmp_path / "api.config.toml").read_text() == (tmp_path / "cli.config.toml").read_text()
    assert res["arrays"]["x_hat"].shape == (2, 61, 12) and (res["arrays"]["n_meas"][:, 10:20] == 0).all()


def test_a_plain_config_on_a_truth_takes_the_scenario_it_records_as_the_verb_does(tmp_path, capsys):
    """A truth of the paper's 3-marker case: `envisat estimate --truth` measures 3 markers (the scenario's
    [measurement] table, which the truth records); so does run_estimate(EstimateConfig(runs=2), ...), once the
    all-markers default (max 8 a step, another Q). A config that sets its own table keeps it."""
    from envisat_pose.filtering.montecarlo import MeasurementConfig
    from envisat_pose.pipelines.campaigns.estimate import EstimateConfig, run_estimate

    truth = tmp_path / "t3.npz"
    assert main(["simulate", "--scenario", "paper-3markers-0.02", "--duration-s", "30", "--out", str(truth),
                 "--quiet"]) == 0
    assert main(["estimate", "--truth", str(truth), "--runs", "2", "--out", str(tmp_path / "cli.npz"),
                 "--quiet"]) == 0
    capsys.readouterr()
    res = run_estimate(EstimateConfig(runs=2), str(tmp_path / "api.npz"), truth_path=str(truth))
    assert res["config"].scenario == "paper-3markers-0.02" and res["arrays"]["n_meas"].max() == 3
    assert (tmp_path / "api.npz").read_bytes() == (tmp_path / "cli.npz").read_bytes()
    own = run_estimate(EstimateConfig(runs=2, measurement=MeasurementConfig(sigma_m=0.05)), str(tmp_path / "own.npz"),
                       truth_path=str(truth))
    assert own["config"].scenario is None and own["arrays"]["n_meas"].max() > 3


# ---------------------------------------------------------------- another target's truth (K keypoints)

@pytest.fixture(scope="module")
def upper_stage_truth(tmp_path_factory):
    """A 60 s truth of the default scenario with the upper stage (models/upper_stage.xml, K = 12), seed 2, written
    by `envisat simulate --target`."""
    path = tmp_path_factory.mktemp("upper") / "run.npz"
    assert main(["simulate", "--target", "models/upper_stage.xml", "--duration-s", "60", "--dt-s", "2", "--seed", "2",
                 "--out", str(path), "--quiet"]) == 0
    return path


def test_truth_file_of_another_target_is_estimated_with_its_keypoints(upper_stage_truth, tmp_path, capsys):
    """`estimate --truth` of the upper stage's truth: the filter measures its 12 keypoints (more than ENVISAT's 8
    at a step) and converges; est.npz names the truth's target."""
    out = tmp_path / "est.npz"
    assert main(["estimate", "--truth", str(upper_stage_truth), "--runs", "3", "--rate-hz", "0.5", "--seed", "1",
                 "--quiet", "--out", str(out)]) == 0
    est = _load(out)
    assert set(est) == KEYS
    assert est["x_hat"].shape == (3, 31, 12) and not est["diverged"].any()
    assert est["n_meas"].max() > 8
    assert np.abs(est["x_hat"][:, -1, :3] - est["x_true"][:, -1, :3]).max() < 0.05
    cfg = json.loads(str(est["config_json"]))
    assert cfg["truth_config"]["target"]["file"] == "models/upper_stage.xml"
    assert cfg["estimate"]["measurement"]["max_markers"] is None  # all visible keypoints
    assert "mean NEES" in capsys.readouterr().out


def test_a_scenario_flown_by_another_target_is_estimated_as_its_simulated_truth(upper_stage_truth, tmp_path):
    """`estimate --scenario default --target FILE` was refused ('a scenario's names its own target') where
    `montecarlo --scenario default --target FILE` runs: a user's own spacecraft needed a `simulate` first. It
    filters the truth `simulate --target` writes (the same keypoints and states), and its written config's header
    names the command with --target that remakes it."""
    out = tmp_path / "est.npz"
    assert main(["estimate", "--scenario", "default", "--target", "models/upper_stage.xml", "--duration-s", "60",
                 "--runs", "1", "--rate-hz", "0.5", "--seed", "2", "--quiet", "--out", str(out)]) == 0
    est = _load(out)
    truth = _load(upper_stage_truth)
    assert est["x_true"].shape == (1, 31, 12) and est["n_meas"].max() > 8
    assert np.allclose(est["x_true"][0], truth["x"], rtol=0, atol=1e-9)
    assert json.loads(str(est["config_json"]))["truth_config"]["target"]["file"] == "models/upper_stage.xml"
    assert ("--scenario default --target models/upper_stage.xml --duration-s 60 --config THIS_FILE"
            in (tmp_path / "est.config.toml").read_text())


def _with_target_record(src, dst, **record):
    from envisat_pose.contracts import TruthTrajectory

    tr = TruthTrajectory.load(str(src))
    config = json.loads(tr.config_json)
    config["target"].update(record)
    tr.config_json = json.dumps(config)
    tr.save(str(dst))


@pytest.mark.parametrize("how, extra, needle", [
    ("sha256", [], "changed since the truth was simulated"),
    ("max_markers", ["--rate-hz", "0.5", "--max-markers", "13"], "--max-markers 13: expected an integer from 1 to 12"),
])
def test_another_targets_truth_errors_are_one_line(upper_stage_truth, tmp_path, capsys, how, extra, needle):
    """A truth that records its target file's sha256 when the file has changed since, and more markers than the
    target's 12 keypoints: exit 2, one line, nothing written."""
    truth = upper_stage_truth
    if how == "sha256":
        truth = tmp_path / "edited.npz"
        _with_target_record(upper_stage_truth, truth, sha256="0" * 64)
    out = tmp_path / "e" / "est.npz"
    capsys.readouterr()
    assert main(["estimate", "--truth", str(truth), "--quiet", "--out", str(out)] + extra) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and needle in err and "Traceback" not in err, err
    assert not out.parent.exists()


def test_runs_started_off_their_p0_are_estimated_with_p0_and_said_to_be(truth_file, tmp_path, capsys):
    """--init-error-scale 5: the filter is told P0 while each run starts 5 x P0's sigmas off. The first update
    measures positions only, so each run's velocity error at t0 is its drawn one: 5 x the consistent run's with the
    same seed; the velocity block's NEES at t0 (mean 3 for a consistent start) is then ~25 x 3."""
    a, b = tmp_path / "one.npz", tmp_path / "five.npz"
    common = ["estimate", "--truth", str(truth_file), "--runs", "40", "--seed", "3", "--quiet"]
    assert main(common + ["--out", str(a)]) == 0
    assert "P0's sigmas off" not in capsys.readouterr().out
    assert main(common + ["--out", str(b), "--init-error-scale", "5"]) == 0
    assert "each run started 5 x P0's sigmas off" in capsys.readouterr().out
    one, five = _load(a), _load(b)
    dv1, dv5 = (e["x_hat"][:, 0, 3:6] - e["x_true"][:, 0, 3:6] for e in (one, five))
    np.testing.assert_allclose(dv5, 5.0 * dv1, rtol=1e-6, atol=1e-12)
    for e in (one, five):  # the filter told the same P0 (its velocity block untouched by the first update)
        np.testing.assert_allclose(e["P"][:, 0, 3:6, 3:6], np.broadcast_to(FilterConfig().P0[3:6, 3:6], (40, 3, 3)),
                                   rtol=1e-6, atol=1e-12)

    def nees_v(e):
        d = e["x_hat"][:, 0, 3:6] - e["x_true"][:, 0, 3:6]
        return np.einsum("ri,rij,rj->r", d, np.linalg.inv(e["P"][:, 0, 3:6, 3:6]), d).mean()

    assert 1.5 < nees_v(one) < 4.5 and nees_v(five) == pytest.approx(25 * nees_v(one), rel=1e-5)
    assert json.loads(str(five["config_json"]))["estimate"]["init_error_scale"] == 5.0


def test_simulate_records_the_target_files_sha256_and_an_edit_since_is_refused(tmp_path, capsys):
    """`simulate --target` records the file's sha256 beside it (once it recorded none, so a truth of an edited
    file, its inertia halved, was filtered with the new file and every run diverged); `estimate --truth` then
    refuses the edited file in one line, and estimates the unedited one."""
    import shutil

    from envisat_pose.contracts import TruthTrajectory
    from envisat_pose.target import load_target, resolve_target_path

    xml = tmp_path / "us.xml"
    shutil.copy(resolve_target_path("models/upper_stage.xml"), xml)  # the packaged file, from any folder
    truth = tmp_path / "run.npz"
    assert main(["simulate", "--target", str(xml), "--duration-s", "20", "--out", str(truth), "--quiet"]) == 0
    recorded = json.loads(TruthTrajectory.load(str(truth)).config_json)["target"]
    assert recorded["file"] == str(xml) and recorded["sha256"] == load_target(str(xml)).sha256
    assert main(["estimate", "--truth", str(truth), "--quiet", "--out", str(tmp_path / "ok.npz")]) == 0
    xml.write_text(xml.read_text() + "\n<!-- edited -->\n")
    out = tmp_path / "e" / "est.npz"
    capsys.readouterr()
    assert main(["estimate", "--truth", str(truth), "--quiet", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "changed since the truth was simulated" in err and not out.parent.exists()


def test_a_truth_file_is_estimated_with_its_scenarios_tables(tmp_path, capsys):
    """`simulate --scenario paper-all-0.2` then `estimate --truth`: the filter takes the scenario the truth records
    (its [measurement] sigma_m 0.2), as `estimate --scenario` would; flags still override it. Once every truth
    file was estimated with the classes' defaults (sigma_m 0.02)."""
    truth = tmp_path / "run.npz"
    assert main(["simulate", "--scenario", "paper-all-0.2", "--duration-s", "20", "--out", str(truth), "--quiet"]) == 0
    out = tmp_path / "est.npz"
    assert main(["estimate", "--truth", str(truth), "--quiet", "--out", str(out)]) == 0
    cfg = json.loads(str(_load(out)["config_json"]))["estimate"]
    assert cfg["scenario"] == "paper-all-0.2" and cfg["measurement"]["sigma_m"] == 0.2
    assert main(["estimate", "--truth", str(truth), "--sigma-m", "0.05", "--quiet", "--out", str(out)]) == 0
    assert json.loads(str(_load(out)["config_json"]))["estimate"]["measurement"]["sigma_m"] == 0.05
