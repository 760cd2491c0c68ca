"""Two jobs writing the same output at the same time, and a job stopped mid-write: what is left must be one
whole job's output or a clear refusal, never a merge of two (an export's folders nested in each other) or a
traceback."""

import os

os.environ.setdefault("MUJOCO_GL", "osmesa")

import pytest

from envisat_pose.config import InputError, from_dict
from envisat_pose.datagen.factory import run_generate
from envisat_pose.datagen.generate_config import GenerateConfig

SMALL = {"num_images": 4, "shard_size": 2, "resolution_px": 64, "seed": 5}


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    out = str(tmp_path_factory.mktemp("concurrent") / "data")
    run_generate(from_dict(GenerateConfig, SMALL), out)
    return out


def _other_export_lands(out_dir):
    """on_shard hook: another export to the same --out finishes while this one runs (its folder appears)."""
    def land(_):
        os.makedirs(os.path.join(out_dir, "images"), exist_ok=True)
        with open(os.path.join(out_dir, "export.json"), "w") as fh:
            fh.write("{}\n")
    return land


@pytest.mark.parametrize("existed", [False, True], ids=["new-folder", "empty-folder"])
def test_an_export_whose_out_was_filled_by_another_export_meanwhile_is_refused_not_merged(dataset, tmp_path,
                                                                                           existed):
    from envisat_pose.pipelines.datasets.export import ExportConfig, export_dataset

    out = str(tmp_path / "coco")
    if existed:
        os.makedirs(out)
    with pytest.raises(InputError, match="another job"):
        export_dataset(dataset, out, ExportConfig(fmt="coco"), on_shard=_other_export_lands(out))
    assert sorted(os.listdir(out)) == ["export.json", "images"]  # the other job's, untouched
    assert os.listdir(os.path.join(out, "images")) == []  # nothing of this export moved into it
    assert [n for n in os.listdir(tmp_path) if n.startswith(".tmp-")] == []  # its staging folder is gone


def test_a_resume_leaves_the_partial_files_of_a_writer_still_running_and_removes_a_killed_ones(tmp_path):
    """Two `envisat generate` on one --out: the second's start removed the first's shard in progress, and the first
    died on a FileNotFoundError traceback. A partial file whose writer runs stays; a killed writer's goes."""
    import subprocess
    import sys

    out = str(tmp_path / "data")

    def stop(_):
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_generate(from_dict(GenerateConfig, SMALL), out, on_shard=stop)
    writer = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    try:
        running = os.path.join(out, f".tmp-{writer.pid}-shard-000001.tar-abcdefgh.tar")
        killed = os.path.join(out, f".tmp-{dead.pid}-shard-000001.tar-ijklmnop.tar")
        for path in (running, killed):
            with open(path, "wb") as fh:
                fh.write(b"partial")
        run_generate(from_dict(GenerateConfig, SMALL), out)
        assert os.path.exists(running) and not os.path.exists(killed)
    finally:
        writer.kill()
        writer.wait()


def test_an_interrupted_simulate_and_estimate_leave_the_earlier_runs_files_as_a_set(tmp_path, monkeypatch):
    """Ctrl-C while the plot is drawn: run.npz and run.config.toml were already replaced by the new seed's while
    run.png stayed the old seed's (a mixed set, the earlier complete run lost). Now nothing moves until all is
    written."""
    import envisat_pose.analysis.plots as plots
    from envisat_pose.datagen.scenario import ScenarioConfig
    from envisat_pose.pipelines.campaigns.estimate import EstimateConfig, run_estimate
    from envisat_pose.pipelines.campaigns.simulate import run_simulate

    def contents(names):
        return {n: (tmp_path / n).read_bytes() for n in names}

    run_simulate(ScenarioConfig(duration_s=5.0, seed=1), str(tmp_path / "run.npz"), plot=True)
    run_estimate(EstimateConfig(runs=2), str(tmp_path / "est.npz"), truth_path=str(tmp_path / "run.npz"), plot=True)
    names = ["run.npz", "run.config.toml", "run.png", "est.npz", "est.config.toml", "est.png"]
    before = contents(names)

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(plots, "plot_states", interrupted)
    monkeypatch.setattr(plots, "plot_estimate", interrupted)
    with pytest.raises(KeyboardInterrupt):
        run_simulate(ScenarioConfig(duration_s=6.0, seed=2), str(tmp_path / "run.npz"), plot=True)
    with pytest.raises(KeyboardInterrupt):
        run_estimate(EstimateConfig(runs=3, seed=4), str(tmp_path / "est.npz"), truth_path=str(tmp_path / "run.npz"),
                     plot=True)
    assert contents(names) == before
    assert sorted(os.listdir(tmp_path)) == sorted(names)  # no staging folder or partial file left


def test_a_rerun_without_the_plot_removes_the_earlier_runs_plot(tmp_path):
    """run.png (est.png) of an earlier run shows another truth (other estimates) than the new run.npz: a rerun
    without plot removes it, as a staged job removes its stale outputs."""
    from envisat_pose.datagen.scenario import ScenarioConfig
    from envisat_pose.pipelines.campaigns.estimate import EstimateConfig, run_estimate
    from envisat_pose.pipelines.campaigns.simulate import run_simulate

    run_simulate(ScenarioConfig(duration_s=5.0, seed=1), str(tmp_path / "run.npz"), plot=True)
    run_estimate(EstimateConfig(runs=2), str(tmp_path / "est.npz"), truth_path=str(tmp_path / "run.npz"), plot=True)
    assert (tmp_path / "run.png").is_file() and (tmp_path / "est.png").is_file()
    run_simulate(ScenarioConfig(duration_s=6.0, seed=2), str(tmp_path / "run.npz"))
    run_estimate(EstimateConfig(runs=2, seed=3), str(tmp_path / "est.npz"), truth_path=str(tmp_path / "run.npz"))
    assert sorted(os.listdir(tmp_path)) == ["est.config.toml", "est.npz", "run.config.toml", "run.npz"]


def test_a_full_disk_is_one_line_with_a_way_on_not_a_traceback(monkeypatch, tmp_path, capsys):
    """Every verb stopped by ENOSPC (a full disk, `ulimit -f`) printed a traceback; its outputs stay whole."""
    import errno

    import envisat_pose.app.simulate as app_simulate
    from envisat_pose.app.cli import main

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(tmp_path / ".tmp-1-run.npz-x.npz"))

    monkeypatch.setattr(app_simulate, "run_pipeline", full)
    assert main(["simulate", "--duration-s", "5", "--out", str(tmp_path / "run.npz")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("envisat simulate: error: No space left on device writing "), err
    assert "run the same command again" in err[0]
