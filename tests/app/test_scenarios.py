"""Named scenarios: the shipped files, their validation, what the verbs take from them, the Earth's shadow
against its closed form, and the rate sweep's outputs and report."""

import json
import math

import numpy as np
import pytest

from envisat_pose import named_scenarios
from envisat_pose.app.cli import build_parser, main
from envisat_pose.config import ConfigError, from_dict

ISSUE_NAMES = ["close-25m", "default", "eclipse", "gravity-gradient", "paper-3markers-0.02", "paper-all-0.02",
               "paper-all-0.2", "pixels-1px", "rate-sweep", "slow-tumble", "stress-tumble"]


def test_the_shipped_scenarios_are_the_issues_and_every_one_validates():
    import dataclasses

    from envisat_pose.datagen.scenario import ScenarioConfig, scenario_config
    from envisat_pose.pipelines.campaigns.campaign import MonteCarloConfig
    from envisat_pose.pipelines.common.job_defaults import scenario_defaults

    assert named_scenarios.names() == ISSUE_NAMES
    # the core's list of truth keys is ScenarioConfig's fields but the job's seed and the scenario's own name
    assert set(named_scenarios.TRUTH_KEYS) == {f.name for f in dataclasses.fields(ScenarioConfig)} - {"seed", "scenario"}
    for name in ISSUE_NAMES:
        scenario_config(name)  # the truth part is a valid ScenarioConfig
        from_dict(MonteCarloConfig, {"scenario": name, **scenario_defaults("montecarlo", name)})  # and its job tables
        assert "\n" not in named_scenarios.scenario_tables(name)["description"]


def test_scenarios_say_what_the_issue_asks():
    from envisat_pose.datagen.scenario import scenario_config
    from envisat_pose.pipelines.common.job_defaults import scenario_defaults

    assert scenario_config("slow-tumble").target.spin_period_s == 226.0
    assert math.isclose(math.degrees(np.linalg.norm(scenario_config("stress-tumble").target.w0_T_rad_s)), 5.0)
    assert scenario_config("close-25m").relative.rho0_C_m == (0.0, 25.0, 0.0)
    assert scenario_config("gravity-gradient").target.gravity_gradient is True
    m = {n: scenario_defaults("estimate", n)["measurement"]
         for n in ("paper-all-0.02", "paper-all-0.2", "paper-3markers-0.02")}
    assert [(v["kind"], v["sigma_m"], v.get("max_markers")) for v in m.values()] == [
        ("markers3d", 0.02, None), ("markers3d", 0.2, None), ("markers3d", 0.02, 3)]  # None: all the target's
    assert scenario_defaults("estimate", "pixels-1px")["measurement"]["kind"] == "pixels"
    rates = named_scenarios.table("rate-sweep", "sweep")["rates_hz"]
    assert min(rates) == 0.05 and max(rates) == 10.0
    # a base's tables are inherited, the child's keys win
    assert scenario_config("paper-all-0.2").orbit == scenario_config("default").orbit
    filters = [scenario_defaults("estimate", n)["filter"] for n in ("paper-all-0.2", "default")]
    assert filters[0] == filters[1]


def test_unknown_names_and_malformed_files_are_one_line(monkeypatch, capsys):
    from envisat_pose.datagen.scenario import scenario_dict

    with pytest.raises(ConfigError) as err:
        scenario_dict("close_25m")  # the old underscore name
    assert "close_25m" in str(err.value) and all(n in str(err.value) for n in ISSUE_NAMES)
    assert main(["montecarlo", "--scenario", "nope", "--out", "x", "--quiet"]) == 2
    assert main(["estimate", "--scenario", "nope", "--quiet"]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 2 and all("--scenario 'nope': expected one of" in ln and "rate-sweep" in ln for ln in lines)

    files = {"a": 'description = "x"\n[measurment]\nkind = "pixels"\n', "b": '[orbit]\ne = 0.1\n',
             "c": 'description = "loop"\nbase = "d"\n', "d": 'description = "loop"\nbase = "c"\n'}
    monkeypatch.setattr(named_scenarios, "_files", lambda: files)
    for name, field in (("a", "measurment"), ("b", "description"), ("c", "base")):
        with pytest.raises(ConfigError) as err:
            named_scenarios.scenario_tables(name)
        assert field in str(err.value) and f"{name}.toml" in str(err.value) and "\n" not in str(err.value)


def test_a_users_scenario_file_runs_where_a_name_does(tmp_path, capsys):
    """A scenario file of the shipped layout, named by its path: `base` taken from a shipped scenario, its own
    orbit and tumble in the campaign's truth, its [measurement] table the campaign's default; a file that is not
    there, or that misspells a table, is one line naming it."""
    path = tmp_path / "my_hold.toml"
    path.write_text('description = "a 60 m hold at 600 km, a 60 s tumble"\nbase = "default"\nduration_s = 60.0\n'
                    '[orbit]\na_m = 6978137.0\n[target]\nspin_period_s = 60.0\n[relative]\nrho0_C_m = [0.0, 60.0, '
                    '0.0]\n[measurement]\nsigma_m = 0.05\n')
    out = tmp_path / "mc"
    assert main(["montecarlo", "--scenario", str(path), "--runs", "3", "--out", str(out), "--quiet"]) == 0
    assert json.loads((out / "summary.json").read_text())["scenario"] == str(path)
    with np.load(out / "truth.npz") as z:
        truth = json.loads(str(z["config_json"]))
    assert truth["orbit"]["a_m"] == 6978137.0 and truth["target"]["spin_period_s"] == 60.0
    assert truth["relative"]["rho0_C_m"] == [0.0, 60.0, 0.0] and truth["orbit"]["i_deg"] == 98.4  # from its base
    assert "sigma_m = 0.05" in (out / "montecarlo.config.toml").read_text()
    missing = tmp_path / "nope.toml"
    assert main(["estimate", "--scenario", str(missing), "--quiet", "--out", str(tmp_path / "e.npz")]) == 2
    path.write_text('description = "x"\n[measurment]\nkind = "pixels"\n')
    assert main(["estimate", "--scenario", str(path), "--quiet", "--out", str(tmp_path / "e.npz")]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 2 and "nope.toml" in lines[0] and "exists" in lines[0]
    assert "measurment" in lines[1] and "my_hold.toml" in lines[1]


def test_scenarios_verb_lists_every_name_with_its_description(capsys):
    assert main(["scenarios"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert [ln.split()[0] for ln in lines] == ISSUE_NAMES
    assert all(len(ln.split(maxsplit=1)) == 2 for ln in lines)
    assert main(["scenarios", "--show", "paper-all-0.2"]) == 0
    assert "sigma_m = 0.2" in capsys.readouterr().out


def test_scenario_tables_are_defaults_under_the_config_file_and_flags(tmp_path):
    from envisat_pose.app import estimate, montecarlo

    parser = build_parser()
    cfg = montecarlo.resolve_config(parser.parse_args(["montecarlo", "--scenario", "paper-all-0.2", "--out", "x"]))
    assert cfg.measurement.sigma_m == 0.2 and cfg.filter.q_sigma == (1e-8, 1e-8, 1e-9, 1e-10)
    (tmp_path / "c.toml").write_text("[measurement]\nsigma_m = 0.05\nmax_markers = 4\n")
    args = ["--scenario", "paper-3markers-0.02", "--config", str(tmp_path / "c.toml"), "--sigma-m", "0.07"]
    for verb, mod in (("montecarlo", montecarlo), ("estimate", estimate)):
        cfg = mod.resolve_config(parser.parse_args([verb, *args, "--out", "x.npz"]))
        assert (cfg.measurement.sigma_m, cfg.measurement.max_markers) == (0.07, 4)  # flag > file > scenario
    assert montecarlo.resolve_config(parser.parse_args(["montecarlo", "--scenario", "eclipse", "--out", "x"])
                                     ).duration_s == 3600.0


def _shadow_share(sun_dir_N, orbit_over=1.0):
    from envisat_pose.datagen.scenario import EclipseConfig, eclipse_windows, scenario_config

    cfg = scenario_config("default")
    cfg = scenario_config("default", duration_s=orbit_over * cfg.orbit.period_s, dt_s=2.0)
    windows = eclipse_windows(cfg, EclipseConfig(tuple(sun_dir_N)))
    return windows, sum(b - a for a, b in windows) / (cfg.n_out * cfg.dt_s)


def test_eclipse_windows_match_the_cylindrical_shadow_in_closed_form():
    """Sun in the orbit plane: the shadow covers asin(R_E / a) / pi of a near-circular orbit (~35 %); sun along
    the orbit normal: no shadow; the eclipse scenario's sun puts one ~2110 s window starting near 600 s."""
    from envisat_pose.datagen.scenario import EARTH_RADIUS_M, scenario_config
    from envisat_pose.pipelines.campaigns.estimate import eclipse_outages

    a, i = 7142.0e3, math.radians(98.4)
    windows, share = _shadow_share((1.0, 0.0, 0.0))  # RAAN 0: N's x axis lies in the orbit plane
    assert len(windows) in (1, 2) and abs(share - math.asin(EARTH_RADIUS_M / a) / math.pi) < 0.005
    assert 0.34 < share < 0.36
    assert _shadow_share((0.0, -math.sin(i), math.cos(i)))[0] == ()  # the orbit normal
    (w,) = eclipse_outages("eclipse", scenario_config("eclipse"))
    assert abs(w[0] - 600.0) < 20.0 and abs((w[1] - w[0]) - math.asin(EARTH_RADIUS_M / a) / math.pi * 6007) < 30.0
    assert eclipse_outages("default", scenario_config("default")) == ()


def test_estimate_on_the_eclipse_scenario_measures_nothing_in_the_shadow(tmp_path):
    """The filter coasts through the outage: no corner used, its covariance grows, and it takes corners again."""
    out = tmp_path / "est.npz"
    assert main(["estimate", "--scenario", "eclipse", "--duration-s", "660", "--runs", "2", "--quiet",
                 "--out", str(out)]) == 0
    with np.load(out) as z:
        t, n, P = z["t_s"], z["n_meas"], z["P"]
        outages = json.loads(str(z["config_json"]))["estimate"]["measurement"]["outages_s"]
    assert len(outages) == 1 and outages[0][1] == 661.0  # the shadow runs past the end of this truth
    dark = t >= outages[0][0]
    assert dark.any() and (n[:, dark] == 0).all() and (n[:, ~dark][:, 1:] > 0).all()
    pos_var = np.trace(P[..., 0:3, 0:3], axis1=-2, axis2=-1)
    assert (np.diff(pos_var[:, dark], axis=1) > 0).all()  # the position covariance grows while coasting


def test_rate_sweep_writes_one_campaign_per_rate_its_figure_and_report(tmp_path):
    import base64

    out, html = tmp_path / "sweep", tmp_path / "r.html"
    args = ["montecarlo", "--scenario", "rate-sweep", "--rates-hz", "2", "0.5", "--runs", "4", "--duration-s", "60",
            "--settle-s", "30", "--block-runs", "2", "--quiet", "--out", str(out)]
    assert main(args) == 0
    s = json.loads((out / "sweep.json").read_text())
    assert s["rates_hz"] == [0.5, 2.0] and s["steps"] == [31, 121] and len(s["rmse"]["position"]) == 2
    for folder in s["campaigns"]:
        sub = json.loads((out / folder / "summary.json").read_text())
        assert sub["measurement"]["rate_hz"] == float(folder[5:-2]) and sub["n_runs"] == 4
    png = (out / "rate_sweep.png").read_bytes()
    assert png.startswith(b"\x89PNG")
    assert main(["report", str(out), str(out / "rate-2hz"), "--out", str(html)]) == 0
    text = html.read_text()
    assert base64.b64encode(png).decode() in text and "Rate sweep" in text and text.count("<tr>") >= 3
    # a single rate with a sweep, or a rate the truth's step cannot divide: one line, before any work
    assert main(args[:-1] + [str(tmp_path / "bad")] + ["--rate-hz", "1"]) == 2
    assert main(args[:4] + ["0.3"] + args[5:-1] + [str(tmp_path / "bad")]) == 2
    assert not (tmp_path / "bad").exists()


@pytest.mark.parametrize("unbuffered", ["1", None])
def test_a_reader_that_goes_away_ends_the_verb_quietly(unbuffered):
    """`envisat scenarios | head -0`: the pipe's reader gone before the verb writes; no traceback (once a
    BrokenPipeError's), the exit status a closed pipe's (141, as a shell reports SIGPIPE). With stdout buffered
    (a user's shell sets no PYTHONUNBUFFERED) the write meets the closed pipe only when the buffer is flushed."""
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k != "PYTHONUNBUFFERED"}
    proc = subprocess.Popen([sys.executable, "-c", "import sys, time; time.sleep(0.5); "
                             "from envisat_pose.app.cli import main; sys.exit(main(['scenarios']))"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            env=env if unbuffered is None else {**env, "PYTHONUNBUFFERED": unbuffered})
    proc.stdout.close()  # the reader is gone before anything is written
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=60) == 141 and "Traceback" not in err and "BrokenPipe" not in err, err
