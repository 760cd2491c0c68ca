"""The corner detector in bfloat16 (DetectConfig.bf16, `envisat run --bf16`): the same corners as in float32 up
to the network's rounding, and the flag carried from the verbs to the detector.

The reference is the same detector in float32 on the same frames (recomputed here, never pinned: bfloat16 kernels
differ between CPUs, and a CPU without native bfloat16 emulates it). On 200 held-out views (seed 9701,
bench/results/detector_bf16.json) the corners both name differ by a median 0.04 px, and PCK@5 moves by at most
1.3 points either way; the bounds below leave room for 3 frames.
"""

import numpy as np
import pytest

from envisat_pose.app.cli import build_parser
from envisat_pose.app.run import resolve_config
from envisat_pose.config import InputError
from envisat_pose.datagen.dataset import iter_samples, sample_image
from envisat_pose.perception.data import crop_resize
from envisat_pose.perception.detect import load_detector
from envisat_pose.perception.evaluate import label_roi
from envisat_pose.perception.weights import shipped_weights_path
from envisat_pose.pipelines.tracking.build import tracker_detector


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    from envisat_pose.app.cli import main

    out = tmp_path_factory.mktemp("bf16") / "ds"
    assert main(["generate", "--num-images", "3", "--seed", "4242", "--out", str(out), "--quiet"]) == 0
    return [(sample_image(m, lab), lab) for _, lab, m in iter_samples(str(out))]


def test_bfloat16_finds_the_float32_corners(frames):
    """The junctions each finds (before naming, whose discrete choices near a tie may go either way: a half-turn
    named the other way moves every corner of a frame) lie where float32 finds them."""
    fp32 = load_detector(shipped_weights_path())
    bf16 = load_detector(shipped_weights_path(), bf16=True)
    assert bf16.cfg.bf16 and not fp32.cfg.bf16 and bf16.cfg.cov_scale == fp32.cfg.cov_scale
    nearest = []
    for image, lab in frames:  # the tracker's path: the region of interest, then the corner patches
        box = label_roi(np.asarray(lab["corners_px"], float), image.shape)
        a = fp32.detect(image, np.asarray(lab["K"]), roi_px=box)
        b = bf16.detect(image, np.asarray(lab["K"]), roi_px=box)
        assert np.all(np.isfinite(b.cov_px[b.visible])) and b.corners_px.dtype == np.float64
        assert len(b.candidates_px) >= 0.75 * len(a.candidates_px)
        d = np.linalg.norm(a.candidates_px[:, None] - b.candidates_px[None], axis=2)
        nearest += list(d.min(axis=1))
        crop = crop_resize(image, box, fp32.cfg.roi_input_px)
        jmap_a, jmap_b = fp32.network(crop, box)["jmap"], bf16.network(crop, box)["jmap"]
        assert 0 < np.abs(jmap_a - jmap_b).max() < 0.25  # bfloat16 did run, and close
    nearest = np.asarray(nearest)
    assert len(nearest) >= 12
    assert np.median(nearest) < 0.2 and np.mean(nearest < 1.0) >= 0.8, np.round(nearest, 3)


def test_the_flag_reaches_the_detector(tmp_path):
    args = build_parser().parse_args(["run", "--scenario", "default", "--bf16", "--out", str(tmp_path / "r")])
    assert resolve_config(args).bf16
    args = build_parser().parse_args(["run", "--scenario", "default", "--out", str(tmp_path / "r")])
    assert not resolve_config(args).bf16
    assert tracker_detector(None, bf16=True).cfg.bf16
    with pytest.raises(InputError, match="^bf16: ENVISAT.s corner detector only"):
        tracker_detector("any.safetensors", target="models/cubesat_3u.xml", bf16=True)
