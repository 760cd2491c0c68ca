"""The pipeline functions as a Python user calls them: paths as str or pathlib.Path alike, one path where a list
of them is taken, a wrong argument one line naming it before any work, the shipped weights by default, and the
caller's process left as it was (torch's and OpenCV's threads, the environment)."""

import os
import pathlib

import numpy as np
import pytest

from envisat_pose.config import InputError


def test_simulate_takes_paths_makes_their_folders_and_names_a_wrong_argument(tmp_path):
    from envisat_pose.datagen.scenario import ScenarioConfig
    from envisat_pose.pipelines.campaigns.simulate import run_simulate

    out = tmp_path / "new" / "sub" / "run.npz"  # a missing folder: made (once a FileNotFoundError of a temp file)
    res = run_simulate(ScenarioConfig(duration_s=5.0), out)
    assert out.is_file() and res["truth_file"] == str(out) and len(res["truth"].t_s) == 6
    with pytest.raises(InputError, match=r"cfg: expected a ScenarioConfig, got NoneType"):
        run_simulate(None, tmp_path / "x.npz")
    with pytest.raises(InputError, match=r"out .*expected a path ending in \.npz"):
        run_simulate(ScenarioConfig(duration_s=5.0), tmp_path / "run.csv")
    assert sorted(os.listdir(tmp_path)) == ["new"]


def test_a_report_takes_one_folder_as_a_list_of_one_and_refuses_none(tmp_path):
    from envisat_pose.pipelines.campaigns.report import write_report

    d = tmp_path / "campaign"
    d.mkdir()
    # the folder, not its first letter
    with pytest.raises(InputError, match="campaign'? is not an `envisat montecarlo` folder"):
        write_report(d, tmp_path / "r.html")
    with pytest.raises(InputError, match="dirs = \\[\\]: expected one or more paths"):
        write_report([], str(tmp_path / "r.html"))
    assert not (tmp_path / "r.html").exists()


def test_a_campaign_runs_on_one_process_by_default_and_refuses_a_runner_of_another_type(tmp_path):
    from envisat_pose.pipelines.campaigns.campaign import MonteCarloConfig, run_campaign

    cfg = MonteCarloConfig(runs=2, duration_s=20.0, settle_s=10.0)
    with pytest.raises(InputError, match="runner: expected a RunnerConfig, got str"):
        run_campaign(cfg, tmp_path / "a", "local")
    assert not (tmp_path / "a").exists()
    summary = run_campaign(cfg, tmp_path / "a")  # a Path; runner None: this process
    assert summary["n_runs"] == 2 and (tmp_path / "a" / "summary.json").is_file()


def test_a_recording_path_of_another_kind_is_refused_alike_by_estimate_and_campaign(tmp_path):
    """The same InputError line for `rrd` from every job that writes a recording (run_campaign said it as a
    ConfigError in other words), before any work."""
    from envisat_pose.pipelines.campaigns.campaign import MonteCarloConfig, run_campaign
    from envisat_pose.pipelines.campaigns.estimate import EstimateConfig, run_estimate

    words = r"^rrd '.*rec\.txt': expected a path ending in \.rrd$"
    rec = tmp_path / "rec.txt"
    with pytest.raises(InputError, match=words) as raised:
        run_estimate(EstimateConfig(scenario="default"), tmp_path / "est.npz", rrd=rec)
    assert type(raised.value) is InputError
    with pytest.raises(InputError, match=words) as raised:
        run_campaign(MonteCarloConfig(runs=2, duration_s=20.0), tmp_path / "mc", rrd=rec)
    assert type(raised.value) is InputError
    assert os.listdir(tmp_path) == []


def test_detect_and_calibrate_configs_take_the_shipped_weights_by_default(tmp_path):
    from envisat_pose.pipelines.common.job_defaults import default_weights_path
    from envisat_pose.pipelines.detector.calibrate import CalibrateJobConfig
    from envisat_pose.pipelines.detector.detect import DetectJobConfig

    assert DetectJobConfig().weights == CalibrateJobConfig().weights == default_weights_path()
    with pytest.raises(InputError, match="weights 'nope': no such file"):
        DetectJobConfig(weights="nope")


def test_the_tracker_takes_a_camera_file_as_a_path_and_a_time_as_a_number(tmp_path):
    from envisat_pose import Tracker

    cam = tmp_path / "cam.toml"
    cam.write_text("fx = 120.0\nfy = 120.0\ncx = 31.5\ncy = 31.5\nwidth = 64\nheight = 64\n")
    tracker = Tracker.from_scenario("default", camera=cam)
    assert (tracker.camera.width_px, tracker.camera.f_px) == (64, 120.0)
    with pytest.raises(InputError, match="camera: expected a camera TOML file or a PinholeCamera, got int"):
        Tracker.from_scenario("default", camera=64)
    with pytest.raises(ValueError, match="t_s = '1': expected the frame's time"):
        tracker.step("1", np.zeros((64, 64), np.uint8))


def test_a_bad_recording_sink_is_refused_before_the_run_makes_its_folder(tmp_path):
    from envisat_pose.pipelines.runs.closed_loop import RunConfig, run_closed_loop

    with pytest.raises(InputError, match="sink 'bogus': expected 'save:PATH', 'spawn' or 'connect:URL'"):
        run_closed_loop(RunConfig(duration_s=5.0), tmp_path / "cl", progress=False, sink="bogus")
    assert not (tmp_path / "cl").exists()


def test_compute_threads_are_given_back():
    import cv2
    import torch

    from envisat_pose.pipelines.common.threads import compute_threads

    t0, c0 = torch.get_num_threads(), cv2.getNumThreads()
    with pytest.raises(RuntimeError):
        with compute_threads(1, 1):
            assert torch.get_num_threads() == 1 and cv2.getNumThreads() == 1
            raise RuntimeError("a job that fails")
    assert (torch.get_num_threads(), cv2.getNumThreads()) == (t0, c0)


def test_compute_threads_refused_leaves_no_block_in_force():
    """A count torch refuses (0) raises on the way in and leaves nothing behind: the next block gives back the
    caller's count (it raised setting the refused count again on its way out, and every later block did too)."""
    import torch

    from envisat_pose.pipelines.common.threads import compute_threads

    t0 = torch.get_num_threads()
    with pytest.raises(RuntimeError):
        with compute_threads(0):
            pass
    assert torch.get_num_threads() == t0
    with compute_threads(1):
        assert torch.get_num_threads() == 1
    assert torch.get_num_threads() == t0


def test_compute_threads_of_two_jobs_that_overlap_in_threads_are_given_back():
    """Two library calls running at once in a thread pool (A starts, B starts, A ends, B ends): the process ends
    with the counts it had before A; a block nested in one thread gives back its outer block's counts."""
    import threading

    import cv2
    import torch

    from envisat_pose.pipelines.common.threads import compute_threads

    t0, c0 = torch.get_num_threads(), cv2.getNumThreads()
    torch.set_num_threads(2)
    cv2.setNumThreads(2)
    try:
        a_in, b_in, a_out = threading.Event(), threading.Event(), threading.Event()

        def job_a():
            with compute_threads(1, 1):
                a_in.set()
                b_in.wait(10)
            a_out.set()

        def job_b():
            a_in.wait(10)
            with compute_threads(1, 1):
                b_in.set()
                a_out.wait(10)

        threads = [threading.Thread(target=job_a), threading.Thread(target=job_b)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(20)
        assert a_out.is_set() and (torch.get_num_threads(), cv2.getNumThreads()) == (2, 2)
        with compute_threads(3, 3):
            with compute_threads(1, 1):
                pass
            assert (torch.get_num_threads(), cv2.getNumThreads()) == (3, 3)
        assert (torch.get_num_threads(), cv2.getNumThreads()) == (2, 2)
    finally:
        torch.set_num_threads(t0)
        cv2.setNumThreads(c0)


def test_paths_are_taken_as_str_or_path():
    from envisat_pose.config import as_path_or_object, path_arg, paths_arg

    assert path_arg(pathlib.Path("a/b"), "out") == "a/b" and paths_arg("a", "dirs") == ["a"]
    assert paths_arg([pathlib.Path("a"), "b"], "dirs") == ["a", "b"] and as_path_or_object(None) is None
    with pytest.raises(InputError, match="out = 3: expected a path"):
        path_arg(3, "out")


def test_an_export_config_error_names_its_python_field():
    from envisat_pose.config import ConfigError
    from envisat_pose.pipelines.datasets.export import ExportConfig

    with pytest.raises(ConfigError, match=r"^fmt = 'x': expected speedplus"):  # the field, not the verb's --format
        ExportConfig("x")


def test_every_pipeline_function_is_quiet_unless_asked():
    import inspect

    import envisat_pose

    defaults = {name: inspect.signature(obj).parameters["progress"].default
                for name, obj in ((n, getattr(envisat_pose, n)) for n in envisat_pose.__all__)
                if inspect.isfunction(obj) and "progress" in inspect.signature(obj).parameters}
    assert len(defaults) >= 10 and set(defaults.values()) == {False}, defaults
