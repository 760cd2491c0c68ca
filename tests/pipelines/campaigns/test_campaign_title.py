"""A campaign's figures say which spacecraft they are of: the target's model name heads every title."""

from envisat_pose.pipelines.campaigns.campaign_config import MonteCarloConfig, campaign_title
from envisat_pose.target import DEFAULT_TARGET, load_target


def test_the_title_names_the_target_the_scenario_and_the_measurement():
    envisat = campaign_title(MonteCarloConfig(scenario="default", runs=3), "3 runs")
    assert envisat.startswith(f"{load_target(DEFAULT_TARGET).name}, scenario default: 3 runs, markers3d at ")
    other = campaign_title(MonteCarloConfig(scenario="default", runs=3, target="models/upper_stage.xml"), "3 runs")
    assert other.startswith(f"{load_target('models/upper_stage.xml').name}, ") and other != envisat
