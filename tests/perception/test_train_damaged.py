"""`envisat train` on a dataset with a damaged shard (issue 41): one line naming it, exit 2, no run folder; with
--skip-damaged it trains on the other shard and records the one it left out. A folder without a manifest whose
shard breaks mid-read stops in the same one line (the worker's error, not its traceback)."""

import json
import os
import shutil

import pytest

from envisat_pose.app.cli import main

DAMAGED = "shard-000001.tar"
SMALL = ["--config", None, "--steps", "2", "--batch-size", "2", "--workers", "0", "--quiet"]
SMALL_TOML = "warmup_steps = 1\n[model]\ninput_px = 128\nwidth = 16\ndepth = 2\nstem_width = 8\n[data]\ninput_px = 128\n"


def damage(path, kind):
    if kind == "truncated":
        os.truncate(path, os.path.getsize(path) // 2)
    else:
        data = bytearray(open(path, "rb").read())
        data[len(data) // 2] ^= 0x01
        open(path, "wb").write(bytes(data))


def small(tmp_path):
    (tmp_path / "small.toml").write_text(SMALL_TOML)
    return [str(tmp_path / "small.toml") if a is None else a for a in SMALL]


@pytest.mark.parametrize("kind", ["truncated", "flipped"])
def test_a_damaged_shard_stops_train_in_one_line_and_skip_damaged_goes_on(tiny_dataset, tmp_path, capsys, kind):
    ds = tmp_path / "ds"
    shutil.copytree(tiny_dataset, ds)
    damage(str(ds / DAMAGED), kind)
    run = tmp_path / "runs" / "det"
    assert main(["train", "--data", str(ds), "--out", str(run), *small(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and DAMAGED in err and "--skip-damaged" in err and "--data" in err, err
    assert not run.exists() and not run.parent.exists()
    assert main(["train", "--data", str(ds), "--out", str(run), "--skip-damaged", *small(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert f"skipped 1 damaged shard(s): ds/{DAMAGED}" in out
    record = json.load(open(run / "config.json"))
    assert record["skipped_damaged_shards"] == [f"ds/{DAMAGED}"]
    manifest = json.load(open(ds / "manifest.json"))
    kept = sum(sh["count"] for sh in manifest["shards"] if sh["name"] != DAMAGED)
    assert record["data"][0]["images"] == kept < manifest["num_images"]  # the images trained on
    assert json.load(open(run / "state.json"))["step"] == 2


def test_a_shard_that_breaks_mid_read_is_one_line_from_a_worker(tiny_dataset, tmp_path, capsys):
    ds = tmp_path / "bare"
    ds.mkdir()
    for name in os.listdir(tiny_dataset):
        if name.endswith(".tar"):
            shutil.copy(os.path.join(tiny_dataset, name), ds / name)  # no manifest: nothing to check first
    damage(str(ds / DAMAGED), "truncated")
    run = tmp_path / "run"
    args = small(tmp_path)
    args[args.index("--workers") + 1] = "1"
    args[args.index("--steps") + 1] = "50"
    assert main(["train", "--data", str(ds), "--out", str(run), *args]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and DAMAGED in err and "Traceback" not in err and "Caught" not in err, err
