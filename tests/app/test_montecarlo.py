"""`envisat montecarlo`: every output file, figures with data, byte-reproducibility across seeds, worker counts
and backends, resuming, the streaming block reduction against the whole-array statistics, one-line errors."""

import json
import os
import shutil
import sys

import numpy as np
import pytest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # the folder's own helpers
from refusals import refused  # noqa: E402

from envisat_pose.app.cli import main  # noqa: E402

BASE = ["montecarlo", "--scenario", "default", "--runs", "20", "--duration-s", "200", "--settle-s", "100",
        "--block-runs", "8", "--seed", "3", "--quiet"]
OUTPUTS = ("truth.npz", "manifest.json", "campaign.npz", "summary.json", "timing.json", "montecarlo.config.toml",
           "envelopes.png", "block_norms.png", "nees_nis.png", "rmse_vs_pcrlb.png")
REPRODUCIBLE = ("summary.json", "campaign.npz", "truth.npz", "blocks/block-0000.npz", "blocks/block-0001.npz",
                "blocks/block-0002.npz")


def _bytes(d, names=REPRODUCIBLE):
    return {n: (d / n).read_bytes() for n in names}


@pytest.fixture(scope="module")
def campaign(tmp_path_factory):
    out = tmp_path_factory.mktemp("mc") / "a"
    assert main(BASE + ["--out", str(out)]) == 0
    return out


def test_campaign_writes_every_file(campaign):
    for name in OUTPUTS:
        assert (campaign / name).is_file(), name
    assert sorted(os.listdir(campaign / "blocks")) == ["block-0000.npz", "block-0001.npz", "block-0002.npz"]
    manifest = json.loads((campaign / "manifest.json").read_text())
    assert manifest["complete"] and [(e["run_start"], e["run_stop"]) for e in manifest["blocks"]] == [
        (0, 8), (8, 16), (16, 20)]
    s = json.loads((campaign / "summary.json").read_text())
    assert s["n_runs"] == 20 and s["steps"] == 201 and s["settle_s"] == 100.0
    assert "wall" not in json.dumps(s)  # timing lives in timing.json only
    assert json.loads((campaign / "timing.json").read_text())["block_wall_s_sum"] > 0
    with np.load(campaign / "campaign.npz") as z:
        assert z["rmse_block"].shape == z["pcrlb_block"].shape == (201, 4)
        assert z["sample_err"].shape == (20, 201, 12) and z["run_rms_block"].shape == (20, 4)
        assert np.isfinite(z["pcrlb_block"]).all() and (z["pcrlb_block"] > 0).all()
    # a converged, consistent filter near the bound (3D corners at 0.02 m)
    assert s["n_diverged"] == 0 and s["diverged_runs"] == [] and s["nis_alarm_alone_runs"] == []
    assert s["rmse"]["position"] < 0.01
    assert s["nees_bounds"][0] * 0.8 < s["nees_mean"] < s["nees_bounds"][1] * 1.2
    for b, ratio in s["rmse_over_pcrlb"].items():
        assert 0.7 < ratio < 1.5, (b, ratio)


def test_figures_decode_and_show_data(campaign):
    from PIL import Image

    for name in ("envelopes.png", "block_norms.png", "nees_nis.png", "rmse_vs_pcrlb.png"):
        img = np.asarray(Image.open(campaign / name).convert("RGB")).astype(int)
        assert img.shape[0] > 300 and img.shape[1] > 300
        non_white = (img < 240).any(-1).mean()
        assert non_white > 0.02, name  # axes, curves and labels, not a blank canvas
        colours = {tuple(c) for c in img[::7, ::7].reshape(-1, 3) // 32}
        assert len(colours) > 4, name
    env = np.asarray(Image.open(campaign / "envelopes.png").convert("RGB")).astype(int)
    grey = (np.abs(env[..., 0] - env[..., 1]) < 8) & (np.abs(env[..., 1] - env[..., 2]) < 8) & (env[..., 0] > 100) & (
        env[..., 0] < 220)
    red = (env[..., 0] > 180) & (env[..., 1] < 80) & (env[..., 2] < 80)
    green = (env[..., 1] > 100) & (env[..., 0] < 100) & (env[..., 2] < 100)
    assert grey.sum() > 1000 and red.sum() > 200 and green.sum() > 200


def test_same_seed_same_bytes_across_workers_and_dask(campaign, tmp_path):
    ref = _bytes(campaign)
    assert main(BASE + ["--workers", "2", "--out", str(tmp_path / "pool")]) == 0
    assert _bytes(tmp_path / "pool") == ref
    assert main(BASE + ["--workers", "2", "--backend", "dask", "--out", str(tmp_path / "dask")]) == 0
    assert _bytes(tmp_path / "dask") == ref
    other = BASE[:-3] + ["--seed", "4", "--quiet"]
    assert main(other + ["--out", str(tmp_path / "seed4")]) == 0
    assert (tmp_path / "seed4" / "summary.json").read_bytes() != ref["summary.json"]


def test_killed_campaign_resumes_to_the_same_bytes(campaign, tmp_path):
    ref = _bytes(campaign)
    d = tmp_path / "resume"
    shutil.copytree(campaign, d)
    for name in ("campaign.npz", "summary.json", "blocks/block-0001.npz"):
        (d / name).unlink()
    (d / "blocks" / "block-0002.npz").write_bytes(b"truncated")  # sha256 no longer matches: redone
    (d / "blocks" / ".tmp-partial.npz").write_bytes(b"x")  # a partial file of the killed run
    kept = (d / "blocks" / "block-0000.npz").stat().st_mtime_ns
    assert main(BASE + ["--out", str(d)]) == 0
    assert _bytes(d) == ref
    assert (d / "blocks" / "block-0000.npz").stat().st_mtime_ns == kept  # a finished block is not redone
    assert not (d / "blocks" / ".tmp-partial.npz").exists()
    assert json.loads((d / "timing.json").read_text())["blocks_run_now"] == 2


def test_a_campaign_stopped_while_its_figures_are_written_is_not_taken_as_finished(campaign, tmp_path,
                                                                                    monkeypatch):
    """Ctrl-C (or a kill) while the figures are drawn: the folder has no summary.json yet, so `report` refuses it
    as unfinished (it once had summary.json and half its figures, which the report took silently); rerunning
    the command finishes it to the same bytes."""
    from envisat_pose.analysis import campaign_figures
    from envisat_pose.config import InputError
    from envisat_pose.pipelines.campaigns.report import load_campaign

    d = tmp_path / "stopped"
    shutil.copytree(campaign, d)
    for name in ("campaign.npz", "summary.json", "timing.json", "nees_nis.png", "rmse_vs_pcrlb.png"):
        (d / name).unlink()

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(campaign_figures, "plot_nees_nis", interrupted)
    assert main(BASE + ["--out", str(d)]) == 130  # the verb's Ctrl-C
    assert not (d / "summary.json").exists() and (d / "campaign.npz").exists()
    with pytest.raises(InputError, match="is an interrupted `envisat montecarlo` campaign .*rerun its command to "
                                         "finish it"):
        load_campaign(str(d))
    monkeypatch.undo()
    assert main(BASE + ["--out", str(d)]) == 0
    assert _bytes(d) == _bytes(campaign)
    assert all((d / name).exists() for name in OUTPUTS)


def test_a_campaign_written_before_a_config_field_existed_resumes(campaign, tmp_path, capsys):
    """A folder whose manifest lacks a field added since (init_error_scale: its runs used 1) resumes as it was;
    the same folder holding another value of it is still refused."""
    ref = _bytes(campaign)
    d = tmp_path / "older"
    shutil.copytree(campaign, d)
    manifest = json.loads((d / "manifest.json").read_text())
    del manifest["config"]["init_error_scale"]
    (d / "manifest.json").write_text(json.dumps(manifest))
    (d / "summary.json").unlink()
    assert main(BASE + ["--out", str(d)]) == 0
    assert _bytes(d) == ref
    manifest["config"]["init_error_scale"] = 2.0
    (d / "manifest.json").write_text(json.dumps(manifest))
    assert main(BASE + ["--out", str(d)]) == 2
    assert "init_error_scale = 2.0 there, 1.0 here" in capsys.readouterr().err


def test_a_folder_of_another_jobs_files_is_refused(campaign, tmp_path, capsys):
    """A campaign into a folder that holds files but no campaign manifest (a simulate's run.npz, a rate sweep):
    one line, nothing written (once it mixed its files in); a campaign killed before its first manifest (its
    truth written, its blocks/ folder made) resumes."""
    d = tmp_path / "sim"
    d.mkdir()
    (d / "run.npz").write_bytes(b"a truth")
    assert main(BASE + ["--out", str(d)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "run.npz" in err[0] and "no manifest.json" in err[0]
    assert sorted(os.listdir(d)) == ["run.npz"]
    early = tmp_path / "early"
    (early / "blocks").mkdir(parents=True)
    shutil.copy(campaign / "truth.npz", early / "truth.npz")
    assert main(BASE + ["--out", str(early)]) == 0
    assert _bytes(early) == _bytes(campaign)


def test_a_sweep_is_refused_where_it_does_not_belong(campaign, tmp_path, capsys):
    """A rate sweep into a campaign's folder, and into a sweep folder of other rates: one line before any work (once
    the first overwrote the campaign's config file and hid it from `report`, the second left the old rates'
    folders beside a sweep.json that no longer listed them)."""
    sweep = BASE[:3] + ["--runs", "2", "--duration-s", "20", "--settle-s", "10", "--quiet"]
    d = tmp_path / "c"
    shutil.copytree(campaign, d)
    assert main(sweep + ["--rates-hz", "1", "0.5", "--out", str(d)]) == 2
    assert "holds a campaign, not a rate sweep" in capsys.readouterr().err
    assert (d / "montecarlo.config.toml").read_bytes() == (campaign / "montecarlo.config.toml").read_bytes()
    s = tmp_path / "sweep"
    assert main(sweep + ["--rates-hz", "1", "0.5", "--out", str(s)]) == 0
    assert main(sweep + ["--rates-hz", "1", "--out", str(s)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "rate-0.5hz" in err[0], err
    assert main(sweep + ["--rates-hz", "1", "0.5", "--out", str(s)]) == 0  # the same sweep: resumed


def test_other_config_in_folder_is_refused(campaign, tmp_path, capsys):
    d = tmp_path / "c"
    shutil.copytree(campaign, d)
    assert main(BASE[:3] + ["--runs", "24"] + BASE[5:] + ["--out", str(d)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "another config" in err[0] and "runs = 20 there, 24 here" in err[0]


@pytest.mark.parametrize("flag, value", [
    ("--runs", "0"), ("--sigma-m", "-1"), ("--block-runs", "0"), ("--settle-s", "500"), ("--rate-hz", "0.3"),
    ("--workers", "0"), ("--scenario", "nope"), ("--init-error-scale", "0"),
    ("--max-markers", "9"),  # ENVISAT's 8 keypoints: once refused after the truth was made
])
def test_bad_value_is_one_error_line_naming_the_flag(tmp_path, capsys, flag, value):
    args = [a for a in BASE]
    if flag in args:
        args[args.index(flag) + 1] = value
    else:
        args += [flag, value]
    assert main(args + ["--out", str(tmp_path / "bad")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"envisat montecarlo: error: {flag} ") and value in err[0], err
    assert not (tmp_path / "bad").exists()


@pytest.mark.parametrize("extra, field", [
    (["--duration-s", "3", "--rate-hz", "0.25"], "--duration-s 3.0"),  # steps at 0 s only; statistics from 1.5 s
    (["--duration-s", "10", "--rate-hz", "0.25", "--settle-s", "9"], "--settle-s 9.0"),  # the last step at 8 s
])
def test_statistics_without_a_step_after_the_settle_time_are_refused(tmp_path, capsys, extra, field):
    """Once such a campaign ran and wrote a summary of NaNs, with numpy's warnings."""
    assert main(["montecarlo", "--scenario", "default", "--runs", "2", *extra, "--out", str(tmp_path / "c")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and field in err[0] and not (tmp_path / "c").exists()


def test_block_reduction_equals_whole_array_statistics(campaign):
    """The chunked, streaming block equals run_filter over the same runs followed by the whole-array statistics."""
    from envisat_pose.analysis.stats import reduce_runs, run_summary
    from envisat_pose.filtering.estimator import diverged_against_truth, nees, run_filter
    from envisat_pose.filtering.montecarlo import make_run_inputs
    from envisat_pose.pipelines.campaigns.campaign import MonteCarloConfig
    from envisat_pose.pipelines.campaigns.campaign_block import CHUNK_STEPS, filter_block, load_campaign_truth

    cfg = MonteCarloConfig(runs=20, duration_s=200.0, settle_s=100.0, block_runs=8, seed=3)
    tr = load_campaign_truth(str(campaign), cfg.measurement)
    assert len(tr.t_s) > CHUNK_STEPS  # more than one chunk
    a, b = 8, 14
    got = filter_block(tr, cfg, a, b)
    inp = make_run_inputs(tr.x_true[0], tr.t_s, tr.z_true, tr.base, cfg.measurement, cfg.filter.P0, cfg.seed, 20)
    res = run_filter(inp.x0_hat[a:b], cfg.filter.P0, tr.t_s, tr.chaser, inp.z[a:b], inp.mask[a:b], inp.R_c,
                     "markers3d", cfg.filter, mu_m3_s2=tr.mu_m3_s2, gravity_gradient=tr.gravity_gradient)
    x_true = np.broadcast_to(tr.x_true, res.x_hat.shape)
    diverged = diverged_against_truth(res.diverged, nees(x_true, res.x_hat, res.P), cfg.filter)
    want = reduce_runs(x_true, res.x_hat, res.P, res.nis, res.dof, diverged, run_start=a).to_arrays()
    for k, v in want.items():
        np.testing.assert_allclose(got[k], v, rtol=1e-9, atol=1e-15, err_msg=k)
    rs = run_summary(tr.t_s, x_true, res.x_hat, res.P, res.nis, res.dof, diverged, settle_s=100.0)
    for k in ("rms_block", "final_block", "max_block", "inside_share", "nees_mean", "nis_per_dof", "diverged"):
        np.testing.assert_allclose(got[f"run_{k}"], getattr(rs, k), rtol=1e-9, err_msg=k)
    # flagged diverged by the filter alone, yet the NEES window rule (recomputed here) holds
    from envisat_pose.state import nees_window_diverged

    nees_rule = nees_window_diverged(nees(x_true, res.x_hat, res.P), cfg.filter.divergence_window,
                                     cfg.filter.divergence_settle_steps, cfg.filter.nees_divergence_factor)
    np.testing.assert_array_equal(got["run_nis_alarm_alone"], res.diverged & ~nees_rule)
    assert got["sample_err"].shape == (b - a, len(tr.t_s), 12)  # runs 8..13 are below sample_runs = 20


def test_a_campaign_in_the_rotation_chart_measures_its_statistics_in_that_chart(campaign):
    """FilterConfig.sigma_chart = 'rotation' (the numpy filter runs it): the block's NEES, Mahalanobis counts and
    divergence rule read the errors in the filter's chart (filtering.ukf.chart_local), as `envisat estimate`
    does: the block equals run_filter over the same runs with NEES recomputed in that chart. The additive
    chart's NEES of the same estimates differs (second order in the errors), so the test tells them apart."""
    import dataclasses

    from envisat_pose.analysis.stats import reduce_runs, run_summary
    from envisat_pose.filtering.estimator import diverged_against_truth, nees, run_filter
    from envisat_pose.filtering.montecarlo import make_run_inputs
    from envisat_pose.filtering.ukf import chart_local
    from envisat_pose.pipelines.campaigns.campaign import MonteCarloConfig
    from envisat_pose.pipelines.campaigns.campaign_block import filter_block, load_campaign_truth

    base = MonteCarloConfig(runs=4, duration_s=200.0, settle_s=100.0, block_runs=4, seed=3)
    cfg = dataclasses.replace(base, filter=dataclasses.replace(base.filter, sigma_chart="rotation"))
    tr = load_campaign_truth(str(campaign), cfg.measurement)
    got = filter_block(tr, cfg, 0, 4)
    inp = make_run_inputs(tr.x_true[0], tr.t_s, tr.z_true, tr.base, cfg.measurement, cfg.filter.P0, cfg.seed, 4)
    res = run_filter(inp.x0_hat, cfg.filter.P0, tr.t_s, tr.chaser, inp.z, inp.mask, inp.R_c, "markers3d",
                     cfg.filter, mu_m3_s2=tr.mu_m3_s2, gravity_gradient=tr.gravity_gradient)
    x_true = np.broadcast_to(tr.x_true, res.x_hat.shape)
    nees_rt = nees(x_true, res.x_hat, res.P, "rotation")
    e_chart = -chart_local(x_true.copy(), res.x_hat)
    diverged = diverged_against_truth(res.diverged, nees_rt, cfg.filter)
    want = reduce_runs(x_true, res.x_hat, res.P, res.nis, res.dof, diverged, e_state=e_chart).to_arrays()
    for k, v in want.items():
        np.testing.assert_allclose(got[k], v, rtol=1e-9, atol=1e-15, err_msg=k)
    rs = run_summary(tr.t_s, x_true, res.x_hat, res.P, res.nis, res.dof, diverged, settle_s=100.0)
    assert not np.allclose(got["run_nees_mean"], rs.nees_mean, rtol=1e-6)  # run_summary: the additive chart
    settled = tr.t_s >= tr.t_s[0] + 100.0
    np.testing.assert_allclose(got["run_nees_mean"], nees_rt[:, settled].mean(1), rtol=1e-9)


def test_a_campaign_started_off_its_p0_draws_wider_and_tells_the_filter_p0(campaign):
    """init_error_scale = 5 reaches the blocks and the single-run history: each kept run's velocity error at t0
    (the first update measures positions only) is 5 x the consistent campaign's, with the same seed."""
    from envisat_pose.pipelines.campaigns.campaign import MonteCarloConfig
    from envisat_pose.pipelines.campaigns.campaign_block import filter_block, filter_run_history, load_campaign_truth

    cfg = MonteCarloConfig(runs=6, duration_s=200.0, settle_s=100.0, block_runs=6, seed=3)
    wide = MonteCarloConfig(runs=6, duration_s=200.0, settle_s=100.0, block_runs=6, seed=3, init_error_scale=5.0)
    tr = load_campaign_truth(str(campaign), cfg.measurement)
    one, five = (filter_block(tr, c, 0, 6)["sample_err"][:, 0, 3:6] for c in (cfg, wide))
    np.testing.assert_allclose(five, 5.0 * one, rtol=1e-6, atol=1e-12)
    x_hat, P = filter_run_history(tr, wide, 2)
    np.testing.assert_allclose(x_hat[0, 3:6] - tr.x_true[0, 3:6], five[2], rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(P[0, 3:6, 3:6], wide.filter.P0[3:6, 3:6], rtol=1e-6, atol=1e-12)


def test_the_public_pipeline_writes_what_the_verb_writes(campaign, tmp_path):
    """The verb is an argument parser over the pipeline: envisat_pose.run_campaign with the config the flags
    resolve to (no CLI) writes the same bytes."""
    import envisat_pose
    from envisat_pose.app.cli import build_parser
    from envisat_pose.app.montecarlo import resolve_config
    from envisat_pose.pipelines.campaigns import (
        campaign as pipeline,  # the config in campaign_config.py, importable here
    )
    from envisat_pose.pools import RunnerConfig

    assert envisat_pose.run_campaign is pipeline.run_campaign and envisat_pose.MonteCarloConfig is \
        pipeline.MonteCarloConfig
    cfg = resolve_config(build_parser().parse_args(BASE + ["--out", "unused"]))
    assert isinstance(cfg, envisat_pose.MonteCarloConfig)
    summary = envisat_pose.run_campaign(cfg, str(tmp_path / "api"), RunnerConfig("local", 1, None, {}))
    assert _bytes(tmp_path / "api") == _bytes(campaign)
    assert summary == json.loads((campaign / "summary.json").read_text())


def test_a_campaign_that_never_measures_says_so(tmp_path, capsys):
    """An R-bar start measured in pixels (the target 50 m above the chaser, outside the V-bar camera's view for 20
    s): the campaign warns that its figures are the prior's, as `envisat estimate` does."""
    from envisat_pose.app.cli import main

    scenario = tmp_path / "rbar.toml"
    scenario.write_text('description = "R-bar, pixels"\nbase = "default"\nduration_s = 20.0\n[relative]\n'
                        'rho0_C_m = [50.0, 0.0, 0.0]\n[measurement]\nkind = "pixels"\n')
    assert main(["montecarlo", "--scenario", str(scenario), "--runs", "3", "--out", str(tmp_path / "mc"),
                 "--quiet"]) == 0
    assert "warning: no step of any run had a measurement" in capsys.readouterr().err


def test_the_help_gives_the_scenarios_duration_as_the_default():
    """`montecarlo --help` once said --duration-s defaults to 1800 s, while the eclipse scenario's campaign runs
    3600 s without it: the help names the scenario's duration as the default, as `estimate --help` does."""
    import contextlib
    import io

    from envisat_pose.app.cli import build_parser
    from envisat_pose.pipelines.jobs import resolve_job

    assert resolve_job("montecarlo", "eclipse", None, {}).duration_s == 3600.0
    text = io.StringIO()
    with contextlib.redirect_stdout(text), pytest.raises(SystemExit):
        build_parser().parse_args(["montecarlo", "--help"])
    help_text = " ".join(text.getvalue().split())
    assert "(default 1800)" not in help_text and "the scenario's, 1800 for default, 3600 for eclipse" in help_text


def test_the_written_config_alone_reruns_the_campaign(campaign, tmp_path, capsys):
    """montecarlo.config.toml records the scenario: given back alone with --config it reruns the campaign to the
    byte (--scenario was required, though the file names it); a file that names none and no flag is one line."""
    from envisat_pose.app.cli import build_parser
    from envisat_pose.app.montecarlo import resolve_config

    written = str(campaign / "montecarlo.config.toml")
    parse = build_parser().parse_args
    assert resolve_config(parse(["montecarlo", "--config", written, "--out", "x"])) == resolve_config(
        parse(BASE + ["--out", "x"]))
    with pytest.warns(UserWarning, match="is not this job's"):
        assert resolve_config(parse(["montecarlo", "--config", written, "--scenario", "slow-tumble", "--out", "x"])
                              ).scenario == "slow-tumble"
    bare = tmp_path / "bare.toml"
    bare.write_text("runs = 2\n")
    assert main(["montecarlo", "--config", str(bare), "--out", str(tmp_path / "b"), "--quiet"]) == 2
    assert "--scenario: required" in capsys.readouterr().err and not (tmp_path / "b").exists()


def test_the_written_config_records_the_target_files_sha256_and_a_rerun_refuses_the_file_changed(tmp_path, capsys):
    """A campaign of a target file: montecarlo.config.toml records the file's sha256 beside it (target_sha256), as
    the manifest does; a rerun from it refuses the file once it changed, in one line naming it and the recorded
    sha256, with nothing written; another --target given over the config's is taken as it is."""
    import tomllib

    from envisat_pose.app.cli import build_parser
    from envisat_pose.app.montecarlo import resolve_config
    from envisat_pose.target import resolve_target_path
    from envisat_pose.target_assets import target_sha256

    target = tmp_path / "cube.xml"  # the smallest shipped target: the quickest visibility table
    shutil.copy(resolve_target_path("models/cubesat_3u.xml"), target)
    first, edited = tmp_path / "first", tmp_path / "edited"
    assert main(BASE[:3] + ["--target", str(target), "--runs", "2", "--duration-s", "20", "--settle-s", "10",
                            "--quiet", "--out", str(first)]) == 0
    written = first / "montecarlo.config.toml"
    recorded = tomllib.loads(written.read_text())["target_sha256"]
    assert recorded == target_sha256(str(target))
    target.write_text(target.read_text() + "<!-- edited since -->\n")
    refused(["montecarlo", "--config", str(written), "--out", str(edited), "--quiet"], capsys, edited,
            "changed since the config was written", str(target), recorded[:12])
    parse = build_parser().parse_args
    assert resolve_config(parse(["montecarlo", "--config", str(written), "--target", "models/cubesat_3u.xml",
                                 "--out", "x"])).target == "models/cubesat_3u.xml"
