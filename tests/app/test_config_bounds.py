"""Finite values no run can mean, refused when the config is built, in one line naming the field, its value and
what is expected (`name = value: expected ...`), before any work: each of these ran to a traceback (a_m = 1e300,
spin_period_s = 1e300, alpha = 1e-300, beta = 1e300, max_rk4_step_s = 1e-300, init_error_scale = 1e-300), to
NaN output with a warning at most (kappa = 1e300, outage_q_scale = 1e300, sun_dir = 1e300), to an error naming
a temporary file or a field the user never set (mu_m3_s2 = 1e300, spin_period_s = 1e-9, frame_dt_s = 1e300), or
to a run of nonsense (a_m = 1e12 beyond the Earth's Hill sphere, an angle of 1e300 deg, an output step or a
frame 1 ns apart). And a rate sweep beside a single `[measurement] rate_hz`, which the sweep replaced unsaid."""

import os
import sys

import pytest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # the folder's own helpers
from refusals import refused  # noqa: E402

SIMULATE = ["simulate", "--duration-s", "10", "--quiet"]
ESTIMATE = ["estimate", "--scenario", "default", "--duration-s", "10", "--runs", "2", "--quiet"]
GENERATE = ["generate", "--num-images", "2", "--resolution", "64", "--quiet"]
SEQUENCE = GENERATE + ["--mode", "sequence"]


@pytest.mark.parametrize("verb, text, words", [
    (SIMULATE, "[orbit]\na_m = 1e12\n", ("orbit.a_m = 1000000000000.0: expected", "Hill sphere")),
    (SIMULATE, "[orbit]\na_m = 1e300\n", ("orbit.a_m = 1e+300: expected", "Hill sphere")),
    (SIMULATE, "[orbit]\nmu_m3_s2 = 1e300\n", ("orbit.mu_m3_s2 = 1e+300: expected", "rad per physics step")),
    (SIMULATE, "[orbit]\nraan_deg = 1e300\n", ("orbit.raan_deg = 1e+300: expected", "[-360, 360] deg")),
    (SIMULATE, "[orbit]\nnu0_deg = -1e300\n", ("orbit.nu0_deg = -1e+300: expected", "[-360, 360] deg")),
    (SIMULATE, "[target]\nspin_period_s = 1e300\n", ("target.spin_period_s = 1e+300: expected", "at most 4.21e+154 s")),
    (SIMULATE, "[target]\nspin_period_s = 1e-9\n", ("target.spin_period_s = 1e-09: expected", "at most 500 rad/s")),
    (SIMULATE, "dt_s = 1e-9\nduration_s = 1e-8\n", ("dt_s = 1e-09: expected", "at least 0.0001 s")),
    (ESTIMATE, "[filter]\nalpha = 1e-300\n", ("filter.alpha = 1e-300: expected", "centre weight")),
    (ESTIMATE, "[filter]\nbeta = 1e300\n", ("filter.beta = 1e+300: expected", "centre weight")),
    (ESTIMATE, "[filter]\nkappa = 1e300\n", ("filter.kappa = 1e+300: expected", "100 standard deviations")),
    (ESTIMATE, "[filter]\nmax_rk4_step_s = 1e-300\n", ("filter.max_rk4_step_s = 1e-300: expected", "0.0001 s")),
    (ESTIMATE, "[filter]\noutage_q_scale = 1e300\n", ("filter.outage_q_scale = 1e+300: expected", "[1, 1e+48]")),
    (ESTIMATE, "init_error_scale = 1e-300\n", ("init_error_scale = 1e-300: expected", "[5.88e-10, 100]")),
    (SEQUENCE, "[sequence]\nframe_dt_s = 1e-9\n", ("sequence.frame_dt_s = 1e-09: expected", "at least 0.0001 s")),
    (SEQUENCE, "[sequence]\nframe_dt_s = 1e300\n", ("sequence.frame_dt_s = 1e+300: expected", "at most 2.5e+06 s")),
    (GENERATE, "sun_dir = [1e300, 1e300, 1e300]\n", ("sun_dir = [1e+300, 1e+300, 1e+300]: expected", "finite length")),
    # numpy asked for TiBs (a traceback after the truth was simulated), or a hang before any output
    (ESTIMATE, "[filter]\ndivergence_window = 1000000000000\n",
     ("filter.divergence_window = 1000000000000: expected", "1 to 100000 steps")),
    (ESTIMATE, "[filter]\nsplit_max = 1000000000000\n", ("filter.split_max = 1000000000000: expected", "1 to 1024")),
    (GENERATE[:1] + GENERATE[3:], "num_images = 1000000000000\n",
     ("num_images = 1000000000000: expected", "1 to 100000000 images")),
])
def test_a_value_no_run_can_mean_is_refused_naming_it(tmp_path, capsys, verb, text, words):
    cfg = tmp_path / "edge.toml"
    cfg.write_text(text)
    out = tmp_path / ("out" if verb[0] == "generate" else "out.npz")
    refused(verb + ["--config", str(cfg), "--out", str(out)], capsys, out, *words)


def test_values_inside_the_bounds_stay_accepted():
    """The bounds sit where a run stops meaning anything, not near the values people use: a GEO orbit, an angle of
    a full turn, the literature's UKF settings (alpha = 1e-3, kappa = 3 - n), a frame at the least physics step."""
    from envisat_pose.datagen.generate_config import GenerateConfig
    from envisat_pose.datagen.scenario import scenario_config
    from envisat_pose.filtering.filter_config import FilterConfig

    scenario_config("default", orbit={"a_m": 42164e3, "e": 0.0, "raan_deg": -360.0, "nu0_deg": 360.0},
                    target={"spin_period_s": 1e9})
    FilterConfig(alpha=1e-3, kappa=0.0)
    FilterConfig(alpha=1.0, kappa=-9.0, beta=2.0)
    FilterConfig(alpha=1e-3, kappa=3.0, outage_q_scale=1e6, max_rk4_step_s=1e-4)
    GenerateConfig(mode="sequence", num_images=2, sequence={"frame_dt_s": 1e-4}, sun_dir=(1e100, 0.0, 0.0))
    FilterConfig(divergence_window=100_000, split_max=1024)
    GenerateConfig(num_images=100_000_000)


def test_a_negative_adapt_seed_is_refused_when_built():
    """numpy's generators take no negative seed: adapt's fine-tune drew from SeedSequence(-1), a ValueError
    traceback after the first track run."""
    from envisat_pose.config import ConfigError
    from envisat_pose.pipelines.adaptation.adapt import AdaptConfig

    with pytest.raises(ConfigError, match=r"^seed = -1: expected a non-negative integer seed below 2\^63"):
        AdaptConfig(seed=-1)
    assert AdaptConfig(seed=2**63 - 1).seed == 2**63 - 1


@pytest.mark.parametrize("given, words", [
    ({"batch_size": 10**12}, r"^batch_size = 1000000000000: expected 1 to 3495 samples per batch"),
    ({"lr": 2.0}, r"^lr = 2.0: expected a learning rate in \[1.18e-38, 1\]"),
])
def test_an_adapt_fine_tune_no_trainer_takes_is_refused_when_built(given, words):
    """The fine-tune's TrainConfig refused these only after the first round's track (minutes of work): the job's
    config refuses them at its build, at the bound of the weights' own network (the shipped one's stem: 3495)."""
    from envisat_pose.config import ConfigError
    from envisat_pose.pipelines.adaptation.adapt import AdaptConfig

    with pytest.raises(ConfigError, match=words):
        AdaptConfig(params="norm_heads", **given)
    assert AdaptConfig(params="all", batch_size=3495, lr=1.0).batch_size == 3495


SWEEP_BESIDE_RATE = "[measurement]\nrate_hz = 2.0\n[sweep]\nrates_hz = [1.0, 0.5]\n"


@pytest.mark.parametrize("text, extra", [
    (SWEEP_BESIDE_RATE, ["--scenario", "default"]),  # both in one file
    ("[measurement]\nrate_hz = 2.0\n", ["--scenario", "default", "--rates-hz", "1", "0.5"]),  # the flag's sweep
    ("[measurement]\nrate_hz = 2.0\n", ["--scenario", "rate-sweep"]),  # the scenario's sweep
])
def test_a_single_rate_beside_a_rate_sweep_is_refused_naming_both(tmp_path, capsys, text, extra):
    cfg = tmp_path / "montecarlo.toml"
    cfg.write_text(text)
    out = tmp_path / "sweep"
    refused(["montecarlo", "--runs", "2", "--duration-s", "20", "--quiet", "--config", str(cfg), "--out", str(out)]
            + extra, capsys, out, "measurement.rate_hz = 2.0: expected", "sweep.rates_hz")
