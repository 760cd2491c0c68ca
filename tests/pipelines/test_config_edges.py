"""A user's config at the edges: values that built a config and then broke the job (a traceback after the truth
was simulated, a message naming a field the user never set) refused when the config is built, naming the field
the user gave, its value and what is expected."""

from __future__ import annotations

import re

import pytest

from envisat_pose.config import ConfigError
from envisat_pose.pipelines.campaigns.estimate import EstimateConfig
from envisat_pose.pipelines.jobs import resolve_job
from envisat_pose.pipelines.tracking.tracker_config import NoiseConfig


@pytest.mark.parametrize("kwargs, field", [
    ({"measurement": {"sigma_m": 1e200}}, "measurement.sigma_m"),  # its square overflowed: OverflowError
    ({"measurement": {"sigma_m": 1e-300}}, "measurement.sigma_m"),  # R singular: LinAlgError
    ({"measurement": {"sigma_px": 1e160}}, "measurement.sigma_px"),
    ({"measurement": {"sigma_range_m": 1e-200}}, "measurement.sigma_range_m"),
    ({"filter": {"p0_sigma": [1e100, 1.0, 1.0, 1.0]}}, "filter.p0_sigma"),  # the prior singular
    ({"filter": {"p0_sigma": [1.0, 1.0, 1.0, 1e-200]}}, "filter.p0_sigma"),
    ({"filter": {"q_sigma": [0.0, 0.0, 0.0, 1e200]}}, "filter.q_sigma"),
])
def test_a_sigma_the_filter_cannot_square_is_refused_when_built(kwargs, field):
    with pytest.raises(ConfigError) as err:
        EstimateConfig(**kwargs)
    assert err.value.field == field and "[1e-12, 1e+12]" in err.value.expected


def test_a_sigma_out_of_bounds_in_a_file_is_refused_naming_it(tmp_path):
    cfg = tmp_path / "huge.toml"
    cfg.write_text("[measurement]\nsigma_m = 1e308\n")
    with pytest.raises(ConfigError, match=r"^measurement\.sigma_m = 1e\+308: expected a positive noise sigma"):
        resolve_job("montecarlo", "default", str(cfg))


def test_sigmas_within_bounds_and_a_zero_process_noise_stay_accepted():
    cfg = EstimateConfig(measurement={"sigma_m": 1e-9}, filter={"q_sigma": [0.0, 0.0, 1e-12, 1e12]})
    assert cfg.measurement.sigma_m == 1e-9 and cfg.filter.q_sigma == (0.0, 0.0, 1e-12, 1e12)
    with pytest.raises(ConfigError, match="detector_q_sigma"):
        NoiseConfig(detector_q_sigma=(0.0, 1e200, 0.0, 0.0))


@pytest.mark.parametrize("kind", ["simulate", "montecarlo"])
def test_a_duration_of_too_many_steps_is_named_with_its_value(kind, tmp_path):
    """duration_s = 1e308 was refused as 'dt_s = 1.0: expected at most 1e7 output steps in duration_s': the field
    and value the user gave were not in the line."""
    cfg = tmp_path / "long.toml"
    cfg.write_text("duration_s = 1e308\n")
    with pytest.raises(ConfigError) as err:
        resolve_job(kind, "default", str(cfg))
    assert (err.value.field, err.value.value) == ("duration_s", 1e308) and "dt_s = 1 s" in err.value.expected


@pytest.mark.parametrize("num_images", [5_000_000, 100_000_000])
def test_a_sequence_too_long_to_simulate_names_num_images(num_images):
    """A sequence's truth takes its duration from num_images: a sequence too long was refused naming dt_s or
    max_physics_dt_s, keys a generate config does not have."""
    from envisat_pose.datagen.generate_config import GenerateConfig

    with pytest.raises(ConfigError) as err:
        GenerateConfig(mode="sequence", num_images=num_images)
    assert (err.value.field, err.value.value) == ("num_images", num_images)
    assert "sequence.frame_dt_s = 1 s" in err.value.expected


def _infinite_builds():
    import math

    from envisat_pose.datagen.scenario import EclipseConfig, ScenarioConfig
    from envisat_pose.filtering.filter_config import FilterConfig
    from envisat_pose.filtering.montecarlo import MeasurementConfig
    from envisat_pose.pipelines.runs.track import TrackConfig
    from envisat_pose.pipelines.tracking.tracker_config import AcquireConfig

    inf = math.inf
    return [(lambda: TrackConfig(rate_hz=inf), "rate_hz"),  # every frame at t = 0 s
            (lambda: FilterConfig(outage_q_scale=inf), "outage_q_scale"),
            (lambda: ScenarioConfig(keepout_margin_m=inf), "keepout_margin_m"),
            (lambda: AcquireConfig(max_gap_s=-inf), "max_gap_s"),
            (lambda: EclipseConfig(sun_dir_N=(inf, 0.0, 0.0)), "sun_dir_N"),
            (lambda: MeasurementConfig(outages_s=((0.0, inf),)), "outages_s")]


@pytest.mark.parametrize("case", range(6))
def test_inf_given_to_a_constructor_is_refused_as_a_file_refuses_it(case):
    """A constructor took inf where from_dict (a config file, a flag) refuses it: a config the file could not
    give, whose written config (inf as JSON's Infinity) no TOML reader takes back."""
    build, field = _infinite_builds()[case]
    with pytest.raises(ConfigError) as err:
        build()
    assert err.value.field == field and err.value.expected == "a finite number"


@pytest.mark.parametrize("text, line", [("runs = 2\nduration_s = 1\nduration_s = 2\n", "line 3 reads 'duration_s = 2'"),
                                        ("[filter]\nalpha = 1\n[filter]\nbeta = 2\n", "line 3 reads '[filter]'")])
def test_a_key_given_twice_names_the_line_that_gives_it_again(tmp_path, text, line):
    """tomllib's own words ('Cannot overwrite a value (at line 3, column 15)') did not name the key."""
    from envisat_pose.config import InputError

    cfg = tmp_path / "twice.toml"
    cfg.write_text(text)
    with pytest.raises(InputError, match=r"^config file '.*twice.toml' is not valid TOML: .*; " + re.escape(line)):
        resolve_job("run", "default", str(cfg))
