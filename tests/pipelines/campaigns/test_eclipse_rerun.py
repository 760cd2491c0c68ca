"""A job of a scenario with an [eclipse] table, rerun from the config it wrote, added the Earth's-shadow windows a
second time: the written config holds them among its measurement outages, and the rerun appended the scenario's
windows again (`envisat montecarlo --config DIR/montecarlo.config.toml` and `envisat estimate --config
est.config.toml`: one window became two). A window an outage already covers is no longer added; a user's own
[measurement] beside the scenario's [eclipse] still gets each window once."""

from envisat_pose.app.cli import main

DURATION_S = 601.0  # the eclipse scenario's shadow begins 600 s in: the shortest truth that reaches it


def written(cfg, path) -> str:
    """cfg's config file as its verb writes it (the fields: to_dict, the run and track jobs' weights by name)."""
    from envisat_pose.config import to_dict, to_toml
    from envisat_pose.pipelines.common.job_defaults import job_record

    path.write_text(to_toml(job_record(cfg) if hasattr(cfg, "weights") else to_dict(cfg)))
    return str(path)


def test_every_jobs_written_config_of_an_eclipse_scenario_rebuilds_that_job(tmp_path):
    from envisat_pose.app import montecarlo
    from envisat_pose.app.cli import build_parser
    from envisat_pose.pipelines.jobs import resolve_job

    for kind in ("montecarlo", "run", "track", "simulate", "estimate"):
        fields = {"duration_s": DURATION_S} if kind in ("montecarlo", "run", "simulate") else {}
        first = resolve_job(kind, "eclipse", **fields)
        assert resolve_job(kind, "eclipse", written(first, tmp_path / f"{kind}.toml")) == first, kind
    campaign = resolve_job("montecarlo", "eclipse", duration_s=DURATION_S)
    assert campaign.measurement.outages_s == ((600.0, 602.0),)
    # as the verb reruns it, `envisat montecarlo --config FILE` (the scenario the file's)
    args = build_parser().parse_args(["montecarlo", "--config", str(tmp_path / "montecarlo.toml"), "--out", "x"])
    assert montecarlo.resolve_config(args) == campaign


def test_a_users_own_measurement_beside_the_scenarios_eclipse_gets_each_window_once(tmp_path):
    from envisat_pose.pipelines.jobs import resolve_job

    own = tmp_path / "own.toml"
    own.write_text("[measurement]\nsigma_m = 0.01\noutages_s = [[100.0, 200.0], [601.0, 602.0]]\n")
    cfg = resolve_job("montecarlo", "eclipse", str(own), duration_s=DURATION_S)
    assert cfg.measurement.sigma_m == 0.01
    # a window of the user's inside the shadow's leaves the shadow's whole window to add
    assert cfg.measurement.outages_s == ((100.0, 200.0), (601.0, 602.0), (600.0, 602.0))
    assert resolve_job("montecarlo", "eclipse", written(cfg, tmp_path / "again.toml")) == cfg


def test_an_estimate_rerun_from_its_written_config_has_each_shadow_window_once(tmp_path):
    a, b = tmp_path / "a" / "est.npz", tmp_path / "b" / "est.npz"
    assert main(["estimate", "--scenario", "eclipse", "--duration-s", f"{DURATION_S:g}", "--out", str(a),
                 "--quiet"]) == 0
    first = (tmp_path / "a" / "est.config.toml").read_text()
    assert "outages_s = [[600.0, 602.0]]" in first
    # the command its truth line names: `envisat estimate --scenario eclipse --duration-s 601 --config THIS_FILE`
    assert main(["estimate", "--scenario", "eclipse", "--duration-s", f"{DURATION_S:g}", "--config",
                 str(tmp_path / "a" / "est.config.toml"), "--out", str(b), "--quiet"]) == 0
    assert (tmp_path / "b" / "est.config.toml").read_text() == first
