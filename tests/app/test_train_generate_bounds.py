"""Finite values no `envisat train` (ENVISAT's corners or --target's keypoints), `generate`, `detect` or `calibrate`
job can mean, refused when the config or flags are read, in one line naming the field, its value and what is
expected, before any weight or image: each ran to a traceback (a line_pool of 0, a width of 100000 asking for
360 GB, lr = 1e300, a seed of -1, a crop margin or jitter of 1e300, 2^63 - 1 samples per batch or torch threads),
to NaN weights blamed on the learning rate (weight_decay, line_jitter_px, a loss weight or focal_alpha at 1e300),
to a run that learns nothing (lr = 1e-300, crops jittered off the image) or to a flat depth image (a depth unit of
1e300 m). A count of 1e300 in a file (301 digits as an int) is no integer a job can hold. Values meaning "off"
stay accepted."""

import os
import sys

import pytest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # the folder's own helpers
from refusals import refused  # noqa: E402

from envisat_pose.config import ConfigError  # noqa: E402

BIG = 2**63 - 1  # TOML's largest integer
KEYPOINTS = ["--target", "models/upper_stage.xml"]


@pytest.mark.parametrize("text, flags, words", [
    ("steps = 1e300\n", [], ("steps = 1e+300: expected an integer within TOML's 64 bits",)),
    (f"batch_size = {BIG}\n", [], (f"batch_size = {BIG}: expected 1 to 3495 samples", "2^31")),
    ("lr = 1e300\n", [], ("lr = 1e+300: expected a learning rate in [1.18e-38, 1]",)),
    ("lr = 1e-300\n", [], ("lr = 1e-300: expected a learning rate in [1.18e-38, 1]", "no weight moves")),
    ("weight_decay = 1e300\n", [], ("weight_decay = 1e+300: expected a decay in [0, 500]", "1 - lr x weight_decay")),
    ("line_jitter_px = 1e300\n", [], ("line_jitter_px = 1e+300: expected pixels in [0, the model's input_px = 320]",)),
    ("seed = -1\n", [], ("seed = -1: expected a non-negative integer seed",)),
    ("[model]\ndepth = 11\n", [], ("model.depth = 11: expected 1 to 10 hourglass levels",)),
    ("[model]\nwidth = 100000\n", [], ("model.width = 100000: expected 1 to 1024 channels",)),
    ("[model]\ninput_px = 8192\n[data]\ninput_px = 8192\n", [], ("model.input_px = 8192: expected at most 4096 px",)),
    ("[model]\nline_pool = 0\n", [], ("model.line_pool = 0: expected a pooling factor of 1 to line_points",)),
    ("[model]\nline_points = 0\n", [], ("model.line_points = 0: expected 1 to input_px (320)",)),
    ("[model]\nline_dim = 0\n", [], ("model.line_dim = 0: expected 1 to 1024 channels",)),
    ("[model]\nn_jtypes = 5\n", [], ("model.n_jtypes = 5: expected 4, the junction types",)),
    ("[data]\ncrop_margin = 1e300\n", [], ("data.crop_margin = 1e+300: expected a factor in [1, 4096]",)),
    ("[data]\ncrop_margin = 0.0\n", [], ("data.crop_margin = 0.0: expected a factor in [1, 4096]",)),
    ("[data]\ncrop_scale_jitter = 1e300\n", [], ("data.crop_scale_jitter = 1e+300: expected a jitter in [0, 8.32]",)),
    ("[data]\ncrop_shift_jitter = 1e300\n", [], ("data.crop_shift_jitter = 1e+300: expected a share",)),
    ("[data]\nsigma_cells = 1e300\n", [], ("data.sigma_cells = 1e+300: expected a heatmap sigma in [0, 80] cells",)),
    ("[data]\nsigma_cells = -1.0\n", [], ("data.sigma_cells = -1.0: expected a heatmap sigma",)),
    ("[data]\nshuffle_buffer = -1\n", [], ("data.shuffle_buffer = -1: expected 0 (no shuffle) to 41943 samples",)),
    (f"[data]\nshuffle_buffer = {BIG}\n", [], (f"data.shuffle_buffer = {BIG}: expected 0 (no shuffle) to 41943 "
                                               "samples", "16 GiB of float32 320 px images")),
    ("[data]\nwhole_frame_prob = -1.0\n", [], ("data.whole_frame_prob = -1.0: expected a probability in [0, 1]",)),
    ("[loss]\nheatmap = 1e300\n", [], ("loss.heatmap = 1e+300: expected a weight in [0, 1e+06]",)),
    ("[loss]\nfocal_alpha = 1e300\n", [], ("loss.focal_alpha = 1e+300: expected an exponent in [0, 22]",)),
    ("[loss]\nvisibility = 1e300\n", KEYPOINTS, ("loss.visibility = 1e+300: expected a weight in [0, 1e+06]",)),
    ("[model]\nwidth = 100000\n", KEYPOINTS, ("model.width = 100000: expected 1 to 1024 channels",)),
])
def test_a_training_value_no_run_can_mean_is_refused_naming_it(tmp_path, text, flags, words):
    """Through the verb's own resolution (app/train.resolve_config: defaults, the file, the flags), before any work."""
    from envisat_pose.app.cli import build_parser
    from envisat_pose.app.train import resolve_config

    cfg = tmp_path / "train.toml"
    cfg.write_text(text)
    args = build_parser().parse_args(["train", "--config", str(cfg), "--out", str(tmp_path / "run"), *flags])
    with pytest.raises(ConfigError) as err:
        resolve_config(args)
    assert all(w in str(err.value) for w in words), str(err.value)


@pytest.mark.parametrize("threads, workers, words", [
    (BIG, None, f"threads = {BIG}: expected 1 to 256 threads"),
    (None, BIG, f"workers = {BIG}: expected 0 (in-process) to 256 worker processes"),
])
def test_trains_threads_and_workers_beyond_any_machine_are_refused(tmp_path, threads, workers, words):
    """2^63 - 1 torch threads (a ValueError from torch after the shards were checked) or DataLoader processes."""
    from envisat_pose.config import InputError
    from envisat_pose.pipelines.detector.train import check_inputs

    data = tmp_path / "data"
    data.mkdir()
    with pytest.raises(InputError, match=words.replace("(", r"\(").replace(")", r"\)")):
        check_inputs([str(data)], str(tmp_path / "run"), False, None, workers, threads)


def test_online_training_refuses_more_renderer_processes_than_any_job_starts():
    from envisat_pose.datagen.generate_config import GenerateConfig
    from envisat_pose.pipelines.detector.train import OnlineConfig

    with pytest.raises(ConfigError, match=rf"online.workers = {BIG}: expected 1 to 256 renderer processes"):
        OnlineConfig(GenerateConfig(), BIG)


def test_detect_refuses_threads_torch_cannot_take_in_one_line(tmp_path, capsys):
    out = tmp_path / "det.npz"
    refused(["detect", "--data", str(tmp_path), "--out", str(out), "--threads", str(BIG), "--quiet"], capsys, out,
            f"--threads {BIG}: expected 1 to 256 threads")


def test_calibrate_refuses_lags_no_sequence_holds():
    """max_lag's sums are arrays of max_lag + 1, allocated after every frame was detected."""
    from envisat_pose.pipelines.detector.calibrate import CalibrateJobConfig

    with pytest.raises(ConfigError, match=rf"max_lag = {BIG}: expected 1 to 200000 lags"):
        CalibrateJobConfig(max_lag=BIG)


def test_generate_refuses_a_depth_unit_longer_than_the_target():
    """depth_scale_m = 1e300 wrote a depth image of zeros; the unit may be at most the target's reach."""
    from envisat_pose.datagen.generate_config import GenerateConfig

    with pytest.raises(ConfigError, match=r"depth_scale_m = 1e\+300: expected a positive scale of at most the "
                                          r"target's reach \(22.\d m"):
        GenerateConfig(depth_scale_m=1e300, num_images=2, resolution_px=64)


def test_off_values_and_the_bounds_themselves_stay_accepted():
    """What means "off" by design (a loss weight 0, sigma_cells 0: one cell, shuffle_buffer 0, line_jitter_px 0,
    focal_beta at any size: the negatives near a peak left out), the bounds (lr 1, weight_decay 1 / lr, a depth of
    10 levels at 4096 px, 256 threads, a shuffle buffer of 16 GiB of images), a run by steps "forever" (2^63 - 1
    steps, checkpoints at its end), a seed of 2^63 - 1, a depth unit of the target's reach."""
    from envisat_pose.datagen.generate_config import GenerateConfig
    from envisat_pose.perception.data import DataConfig
    from envisat_pose.perception.keypoint_train import KeypointTrainConfig
    from envisat_pose.perception.losses import LossConfig
    from envisat_pose.perception.model import ModelConfig
    from envisat_pose.perception.train import TrainConfig
    from envisat_pose.pipelines.detector.calibrate import CalibrateJobConfig

    TrainConfig(lr=1.0, weight_decay=1.0, seed=BIG, steps=BIG, checkpoint_every=BIG, warmup_steps=BIG,
                line_jitter_px=0.0, loss=LossConfig(heatmap=0.0, nll=0.0, focal_beta=1e300, focal_alpha=22.0),
                data=DataConfig(sigma_cells=0.0, shuffle_buffer=0, crop_margin=1.0, whole_frame_prob=1.0))
    TrainConfig(model=ModelConfig(input_px=4096, depth=10, width=1024), data=DataConfig(input_px=4096), batch_size=1)
    DataConfig(shuffle_buffer=41943)
    DataConfig(input_px=4096, shuffle_buffer=256)
    KeypointTrainConfig(target="models/upper_stage.xml", lr=1e-12)
    CalibrateJobConfig(max_lag=200_000)
    GenerateConfig(depth_scale_m=22.0, num_images=2, resolution_px=64)
