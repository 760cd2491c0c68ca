"""Outputs made with the shipped detector weights name them 'models/detector.safetensors' (SHIPPED_WEIGHTS) beside
their sha256, not by the path of the machine they were made on (it was absolute in det.npz's config_json, evaluate's
JSON, run's and track's summary.json and written configs): that name is what the verbs take back (--weights, a
written config's `weights`), the same file wherever the package is installed. Weights a user gives keep the path
given. Each test runs from an empty folder of its own with relative paths, so an absolute path in an output is one
of this machine's."""

import json
import shutil

import numpy as np

from envisat_pose.app.cli import build_parser, main
from envisat_pose.io import sha256_file
from envisat_pose.pipelines.common.job_defaults import SHIPPED_WEIGHTS, default_weights_path, weights_file, weights_name
from envisat_pose.provenance import find_absolute_paths


def machine_free(text: str, what: str) -> None:
    assert find_absolute_paths(text) == [], (what, find_absolute_paths(text))


def names_the_shipped_weights(record: dict) -> None:
    """The record names the shipped weights by SHIPPED_WEIGHTS, which resolves to the file of its sha256."""
    assert record["weights"] == SHIPPED_WEIGHTS
    assert sha256_file(weights_file(record["weights"])) == record["weights_sha256"] == sha256_file(
        default_weights_path())


def test_the_shipped_weights_name_resolves_from_anywhere_and_given_weights_keep_their_path(tmp_path):
    assert weights_name(default_weights_path()) == SHIPPED_WEIGHTS  # no models/ folder here: the package's
    assert weights_file(SHIPPED_WEIGHTS) == weights_file("") == default_weights_path()
    mine = tmp_path / "mine.safetensors"
    shutil.copy(default_weights_path(), mine)
    assert weights_name(str(mine)) == str(mine) and weights_file(str(mine)) == str(mine)
    other = weights_file("models/upper_stage_detector.safetensors")  # another shipped file, by the same rule
    assert weights_name(other) == "models/upper_stage_detector.safetensors"


def test_detect_and_evaluate_name_the_shipped_weights_by_their_package_name():
    assert main(["generate", "--num-images", "1", "--resolution", "64", "--out", "data", "--quiet"]) == 0
    assert main(["detect", "--data", "data", "--out", "det.npz", "--quiet"]) == 0
    assert main(["evaluate", "--data", "data", "--json", "eval.json", "--quiet"]) == 0
    with np.load("det.npz") as z:
        config = str(z["config_json"])
    machine_free(config, "det.npz")
    names_the_shipped_weights(json.loads(config))
    with open("eval.json", encoding="utf-8") as fh:
        text = fh.read()
    machine_free(text, "eval.json")
    names_the_shipped_weights(json.loads(text))


def read(path: str) -> str:
    with open(path, encoding="utf-8") as fh:
        return fh.read()


def test_run_and_track_name_the_shipped_weights_and_their_written_configs_take_the_name_back():
    from envisat_pose.app.run import resolve_config

    assert main(["run", "--duration-s", "1", "--out", "run", "--quiet"]) == 0
    assert main(["generate", "--mode", "sequence", "--num-images", "3", "--resolution", "64", "--out", "frames",
                 "--quiet"]) == 0
    with open("fast.toml", "w", encoding="utf-8") as fh:
        fh.write("[tracker.acquire]\nframes = 3\n")  # the cold start's frames: what is checked is the outputs
    assert main(["track", "--images", "frames", "--config", "fast.toml", "--out", "track", "--quiet"]) == 0
    for job, written in (("run", "run.config.toml"), ("track", "track.config.toml")):
        names_the_shipped_weights(json.loads(read(f"{job}/summary.json")))
        for name in ("summary.json", written):
            machine_free(read(f"{job}/{name}"), f"{job}/{name}")
        for name in ("det.npz", "est.npz"):
            with np.load(f"{job}/{name}") as z:
                machine_free(str(z["config_json"]), f"{job}/{name}")
    parse = build_parser().parse_args
    again = resolve_config(parse(["run", "--config", "run/run.config.toml", "--out", "x"]))
    assert again.weights == default_weights_path()
    assert again == resolve_config(parse(["run", "--duration-s", "1", "--out", "x"]))
