"""A truth simulated in Python from a named scenario records that scenario, as the verb's does: the
ScenarioConfig made by scenario_config or resolve_job carries its name (`scenario`), so `estimate` of that truth
takes the scenario's filter and measurement tables (before, only run_simulate's `label` recorded it, and a truth
made without one was estimated with the classes' defaults)."""

import json

import numpy as np
import pytest

from envisat_pose.config import ConfigError
from envisat_pose.datagen.scenario import ScenarioConfig, scenario_config, scenario_of_truth
from envisat_pose.pipelines.campaigns.estimate import EstimateConfig, recorded_scenario, with_recorded_scenario
from envisat_pose.pipelines.campaigns.simulate import run_simulate
from envisat_pose.pipelines.jobs import resolve_job


def _config_json(path) -> dict:
    with np.load(path, allow_pickle=False) as z:
        return json.loads(str(z["config_json"]))


def test_a_named_scenarios_config_carries_its_name_and_an_unknown_name_is_refused():
    assert scenario_config("eclipse").scenario == "eclipse"
    assert resolve_job("simulate", "slow-tumble", duration_s=5.0).scenario == "slow-tumble"
    assert ScenarioConfig().scenario == ""
    with pytest.raises(ConfigError, match="scenario"):
        ScenarioConfig(scenario="no-such-scenario")


def test_a_python_made_truth_records_its_scenario_and_estimate_takes_its_tables(tmp_path):
    out = tmp_path / "run.npz"
    run_simulate(resolve_job("simulate", "eclipse", duration_s=5.0, seed=2), out)  # no label
    assert recorded_scenario(str(out)) == "eclipse"
    cfg = with_recorded_scenario(EstimateConfig(), str(out))
    assert cfg.scenario == "eclipse" and cfg == EstimateConfig(scenario="eclipse")
    assert scenario_of_truth(_config_json(out)).scenario == "eclipse"
    assert "scenario = \"eclipse\"" in (tmp_path / "run.config.toml").read_text(encoding="utf-8")


def test_a_truth_of_no_named_scenario_records_none_as_before(tmp_path):
    out = tmp_path / "plain.npz"
    run_simulate(ScenarioConfig(duration_s=5.0), out)
    assert "scenario" not in _config_json(out) and recorded_scenario(str(out)) is None
    assert with_recorded_scenario(EstimateConfig(), str(out)) == EstimateConfig()


def test_a_label_that_contradicts_the_configs_scenario_is_refused_having_written_nothing(tmp_path):
    """cfg made from 'eclipse' with label 'default': the truth recorded 'default', and estimate --truth then took
    default's tables for an eclipse truth. Refused, naming `label`; the same name, or none, goes on."""
    from envisat_pose.config import InputError

    out = tmp_path / "run.npz"
    with pytest.raises(InputError, match=r"^label 'default': cfg was made from scenario 'eclipse'"):
        run_simulate(scenario_config("eclipse", duration_s=5.0), out, label="default")
    assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == []
    run_simulate(scenario_config("eclipse", duration_s=5.0), out, label="eclipse")
    assert recorded_scenario(str(out)) == "eclipse"
