"""A campaign's figures say which spacecraft they are of: the target's model name heads every title."""

from envisat_pose.pipelines.campaigns.campaign_config import MonteCarloConfig, campaign_title
from envisat_pose.target import DEFAULT_TARGET, load_target


def test_the_title_names_the_target_the_scenario_and_the_measurement():
    envisat = campaign_title(MonteCarloConfig(scenario="default", runs=3), "3 runs")
    assert envisat.startswith(f"{load_target(DEFAULT_TARGET).name}, scenario default: 3 runs, markers3d at ")
    other = campaign_title(MonteCarloConfig(scenario="default", runs=3, target="models/upper_stage.xml"), "3 runs")
    assert other.startswith(f"{load_target('models/upper_stage.xml').name}, ") and other != envisat


def test_an_estimates_figure_names_its_truths_target(tmp_path, monkeypatch):
    """`envisat estimate`'s PNG of another target's truth says which spacecraft it is of (it said only the
    measurement), as ENVISAT's says ENVISAT's name."""
    from envisat_pose.analysis import plots
    from envisat_pose.datagen.scenario import scenario_config
    from envisat_pose.datagen.truth import simulate_truth
    from envisat_pose.pipelines.campaigns.estimate import EstimateConfig, run_estimate

    titles = []
    monkeypatch.setattr(plots, "plot_estimate", lambda *a, title=None, **k: titles.append(title))
    for file in (DEFAULT_TARGET, "models/upper_stage.xml"):
        truth = tmp_path / f"{len(titles)}.npz"
        simulate_truth(scenario_config("default", duration_s=20.0, seed=3, target={"file": file})).save(str(truth))
        run_estimate(EstimateConfig(runs=1), str(tmp_path / f"est{len(titles)}.npz"), truth_path=str(truth), plot=True)
    names = [load_target(f).name for f in (DEFAULT_TARGET, "models/upper_stage.xml")]
    assert [t.split(":")[0] for t in titles] == names and names[0] != names[1]


def test_a_truths_plot_counts_its_targets_own_keypoints(tmp_path, monkeypatch):
    """`envisat simulate --plot` of another target counts its "keypoints" (ENVISAT's: its "corners"), each out of
    the target's own K (the CubeSat's 12, not ENVISAT's 8)."""
    from envisat_pose.analysis import plots
    from envisat_pose.datagen.scenario import scenario_config
    from envisat_pose.pipelines.campaigns.simulate import run_simulate

    drawn = []
    monkeypatch.setattr(plots, "plot_states", lambda t_s, x, path, visible=None, points="corners", **k:
                        drawn.append((points, visible.shape[1])))
    for file in (DEFAULT_TARGET, "models/cubesat_3u.xml"):
        cfg = scenario_config("default", duration_s=4.0, seed=1, target={"file": file})
        run_simulate(cfg, str(tmp_path / f"{len(drawn)}.npz"), plot=True)
    assert drawn == [("corners", 8), ("keypoints", load_target("models/cubesat_3u.xml").num_keypoints)]
