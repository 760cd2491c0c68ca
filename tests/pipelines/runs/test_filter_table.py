"""A run's or a track's [filter] table given in Python as a dict sets its keys over the scenario's filter (the
tracker's settings, TRACKER_FILTER, under the scenario's table), as the same table in a config file does and as
the Tracker's own filter_config does: it was read over the plain UKF's defaults, so one key turned the tracker's
adaptive R, gate lockout and visibility check back to the estimator's."""

import dataclasses

import pytest

from envisat_pose import RunConfig, TrackConfig
from envisat_pose.pipelines.jobs import resolve_job
from envisat_pose.pipelines.tracking.build import tracker_filter


@pytest.mark.parametrize("cls, kind", [(RunConfig, "run"), (TrackConfig, "track")])
@pytest.mark.parametrize("scenario", ["default", "stress-tumble"])
def test_a_filter_dict_sets_its_keys_over_the_scenarios_filter_as_a_config_file_does(cls, kind, scenario):
    given = cls(scenario=scenario, filter={"gate_prob": 0.999}).filter
    assert given == resolve_job(kind, scenario, None, {"filter.gate_prob": 0.999}).filter
    assert given == tracker_filter({"gate_prob": 0.999}, scenario)  # the Tracker's filter_config={...}
    assert given.gate_prob == 0.999 and given.adaptive_r and given.visibility_from == "mean"
    # a whole table (a run.config.toml read back) is taken as it is
    whole = cls(scenario=scenario).filter
    assert cls(scenario=scenario, filter=dataclasses.asdict(whole) | {"adaptive_r": False}).filter.adaptive_r is False


def test_a_tracks_orbit_dict_sets_its_keys_over_the_scenarios_orbit(tmp_path):
    scenario = tmp_path / "high.toml"
    scenario.write_text('description = "a higher hold"\nbase = "default"\n[orbit]\na_m = 7500000.0\ne = 0.002\n')
    given = TrackConfig(scenario=str(scenario), orbit={"nu0_deg": 10.0}).orbit
    assert given == resolve_job("track", str(scenario), None, {"orbit.nu0_deg": 10.0}).orbit
    assert (given.a_m, given.e, given.nu0_deg) == (7500000.0, 0.002, 10.0)
