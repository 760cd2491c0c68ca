"""Every reader of a generated dataset (issue 41): a shard truncated to half its size or with one bit flipped is
one line naming it (exit 2, nothing written), before any work; with --skip-damaged the verb goes on without it, its
result made of the other shard alone, and names it in its output and its record. A shard that fails while being
read (a folder without a manifest: nothing to check it against first) is the same one line."""

import hashlib
import json
import os
import shutil

import numpy as np
import pytest
import torch

from envisat_pose.app.cli import main
from envisat_pose.perception.detect import FrameDetection
from envisat_pose.perception.model import CornerNet, ModelConfig
from envisat_pose.perception.weights import read_metadata, save_weights

DAMAGED = "shard-000001.tar"


def damage(path: str, kind: str) -> None:
    """Truncate the file to half its size, or flip one bit in its middle."""
    if kind == "truncated":
        os.truncate(path, os.path.getsize(path) // 2)
    else:
        data = bytearray(open(path, "rb").read())
        data[len(data) // 2] ^= 0x01
        open(path, "wb").write(bytes(data))


@pytest.fixture(params=["truncated", "flipped"])
def damaged_set(request, tiny_dataset, tmp_path):
    """A copy of the tiny dataset (2 shards of 4) whose second shard is damaged."""
    ds = tmp_path / "ds"
    shutil.copytree(tiny_dataset, ds)
    damage(str(ds / DAMAGED), request.param)
    return ds


@pytest.fixture(scope="module")
def tiny_weights(tmp_path_factory):
    torch.manual_seed(0)  # this module's untrained model: fast, names what it names
    w = tmp_path_factory.mktemp("w") / "w.safetensors"
    save_weights(str(w), CornerNet(ModelConfig(input_px=64, width=16, depth=2, stem_width=8)))
    return str(w)


def refused(args, capsys, *outputs):
    """The verb stops in one line naming the damaged shard, exit 2, and writes none of outputs."""
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and DAMAGED in err and "damaged" in err and "--skip-damaged" in err, err
    for out in outputs:
        assert not os.path.exists(out), out


def first_shard_keys(ds) -> list[str]:
    manifest = json.loads((ds / "manifest.json").read_text())
    n = manifest["shards"][0]["count"]
    return [f"{k:09d}" for k in range(n)]


def test_inspect(damaged_set, tmp_path, capsys):
    montage = tmp_path / "m" / "montage.png"
    refused(["dataset", "inspect", str(damaged_set), "--montage", str(montage)], capsys, montage, tmp_path / "m")
    assert main(["dataset", "inspect", str(damaged_set), "--montage", str(montage), "--skip-damaged"]) == 0
    out = capsys.readouterr().out
    stats = json.loads(out[:out.index("\n}\n") + 2])
    assert stats["samples"] == len(first_shard_keys(damaged_set)) and stats["skipped_damaged_shards"] == [DAMAGED]
    assert f"skipped 1 damaged shard(s): {DAMAGED}" in out and montage.is_file()


def test_detect(damaged_set, tiny_weights, tmp_path, capsys):
    out = tmp_path / "det" / "det.npz"
    args = ["detect", "--weights", tiny_weights, "--data", str(damaged_set), "--out", str(out), "--quiet",
            "--threads", "1"]
    refused(args, capsys, out, tmp_path / "det")
    assert main(args + ["--skip-damaged"]) == 0
    assert DAMAGED in capsys.readouterr().out
    with np.load(out, allow_pickle=False) as z:
        assert z["key"].tolist() == first_shard_keys(damaged_set)
        assert json.loads(str(z["config_json"]))["skipped_damaged_shards"] == [DAMAGED]


def test_evaluate(damaged_set, tiny_weights, tmp_path, capsys):
    out = tmp_path / "ev" / "eval.json"
    args = ["evaluate", "--weights", tiny_weights, "--data", str(damaged_set), "--json", str(out), "--quiet",
            "--threads", "1"]
    refused(args, capsys, out, tmp_path / "ev")
    assert main(args + ["--skip-damaged"]) == 0
    assert DAMAGED in capsys.readouterr().out
    result = json.loads(out.read_text())
    assert result["frames"] == len(first_shard_keys(damaged_set)) and result["skipped_damaged_shards"] == [DAMAGED]


class LabelLookupDetector:
    """Test double: each frame's labelled visible corners (found by the frame's pixels) plus Gaussian noise of
    sigma 1 px, claiming sigma 0.5 px."""

    def __init__(self, labels: dict):
        self.labels, self.rng = labels, np.random.default_rng(0)

    def detect(self, image, K, roi_px=None, prior_R_cam_from_target=None):
        label = self.labels[hashlib.sha1(image.tobytes()).hexdigest()]
        use = label["visible"] & label["in_frame"]
        pts = np.where(use[:, None], label["corners_px"] + self.rng.normal(0, 1.0, (8, 2)), np.nan)
        cov = np.where(use[:, None, None], 0.25 * np.eye(2), np.nan)
        return FrameDetection(pts, cov, use * 1.0, use, pts, 0.0, False, np.zeros(3), pts)


def test_calibrate(damaged_set, tiny_dataset, tiny_weights, tmp_path, capsys, monkeypatch):
    import envisat_pose.perception.detect as pd
    from envisat_pose.perception.data import shard_paths
    from envisat_pose.pipelines.detector.detect import camera_samples

    samples = list(camera_samples(shard_paths(tiny_dataset)))
    monkeypatch.setattr(pd, "load_detector", lambda *a, **k: LabelLookupDetector(
        {hashlib.sha1(img.tobytes()).hexdigest(): lab for _, img, lab in samples}))
    out = tmp_path / "cal" / "c.safetensors"
    # the folder three times: enough corners from its first shard alone
    args = ["calibrate", "--weights", tiny_weights, "--data", *[str(damaged_set)] * 3, "--out", str(out), "--quiet",
            "--threads", "1"]
    refused(args, capsys, out, tmp_path / "cal")
    assert main(args + ["--skip-damaged"]) == 0
    assert f"skipped 1 damaged shard(s): ds/{DAMAGED}" in capsys.readouterr().out
    record = json.loads(read_metadata(str(out))["cov_calibration"])
    first = [lab for key, _, lab in samples if key in first_shard_keys(damaged_set)]
    assert record["corners"] == 3 * sum(int(np.sum(lab["visible"] & lab["in_frame"])) for lab in first)
    assert record["skipped_damaged_shards"] == [f"ds/{DAMAGED}"]


def test_a_shard_failing_mid_run_is_one_line(tiny_dataset, tiny_weights, tmp_path, capsys):
    """Without a manifest nothing is checked first: the truncated shard stops the run when it is read."""
    ds = tmp_path / "nomanifest"
    shutil.copytree(tiny_dataset, ds)
    os.remove(ds / "manifest.json")
    size = os.path.getsize(ds / DAMAGED)
    os.truncate(ds / DAMAGED, size // 2 + 700)  # inside a member's data, not on a header's boundary
    out = tmp_path / "det.npz"
    assert main(["detect", "--weights", tiny_weights, "--data", str(ds), "--out", str(out), "--quiet",
                 "--threads", "1"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and f"{DAMAGED}' cannot be read" in err, err
    assert not out.exists()


def test_an_image_that_breaks_mid_read_is_one_line_in_inspect(tiny_dataset, tmp_path, capsys):
    """A shard whose manifest was rewritten to match it (nothing to catch first) and whose first PNG is garbage,
    or whose first sample has no PNG: `dataset inspect` stops in one line naming the sample."""
    import io
    import tarfile

    for case in ("garbage", "missing"):
        ds = tmp_path / case
        shutil.copytree(tiny_dataset, ds)
        src = tarfile.open(ds / DAMAGED)
        members = [(m, src.extractfile(m).read()) for m in src.getmembers()]
        src.close()
        first_png = next(m.name for m, _ in members if m.name.endswith(".png") and m.name.count(".") == 1)
        with tarfile.open(ds / DAMAGED, "w") as dst:
            for m, data in members:
                if m.name == first_png:
                    if case == "missing":
                        continue
                    data = b"\x89PNG not really" + bytes(64)
                m.size = len(data)
                dst.addfile(m, io.BytesIO(data))
        manifest = json.loads((ds / "manifest.json").read_text())
        for sh in manifest["shards"]:  # the manifest made to match: nothing to catch before the read
            if sh["name"] == DAMAGED:
                sh["bytes"] = os.path.getsize(ds / DAMAGED)
                sh["sha256"] = hashlib.sha256((ds / DAMAGED).read_bytes()).hexdigest()
        (ds / "manifest.json").write_text(json.dumps(manifest))
        assert main(["dataset", "inspect", str(ds), "--count", "8"]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "png" in err and "Traceback" not in err, err


@pytest.fixture(scope="module")
def sequence_set(tmp_path_factory):
    """6 frames of 128 px in 2 shards of 3, `envisat generate --mode sequence`."""
    out = tmp_path_factory.mktemp("seq") / "seq"
    assert main(["generate", "--mode", "sequence", "--num-images", "6", "--shard-size", "3", "--resolution", "128",
                 "--seed", "2", "--out", str(out), "--quiet"]) == 0
    return out


@pytest.mark.parametrize("kind", ["truncated", "flipped"])
def test_track_on_a_generate_folder(sequence_set, kind, tmp_path, capsys):
    ds = tmp_path / "seq"
    shutil.copytree(sequence_set, ds)
    damage(str(ds / DAMAGED), kind)
    cfg = tmp_path / "fast.toml"
    cfg.write_text("[tracker.acquire]\nframes = 3\n")
    out = tmp_path / "runs" / "t"
    args = ["track", "--images", str(ds), "--config", str(cfg), "--out", str(out), "--quiet"]
    refused(args, capsys, out, tmp_path / "runs")
    assert main(args + ["--skip-damaged"]) == 0
    assert f"skipped 1 damaged shard(s): {DAMAGED}" in capsys.readouterr().out
    summary = json.loads((out / "summary.json").read_text())
    assert summary["source"]["frames"] == 3 and summary["source"]["skipped_damaged_shards"] == [DAMAGED]
    with np.load(out / "est.npz", allow_pickle=False) as z:
        assert len(z["t_s"]) == 3
