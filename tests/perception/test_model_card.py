"""The model card travels (issue 26, item 4): no absolute path of the machine that made it, in
models/detector.json or in the shipped weights' metadata; scripts/model_card.py refuses a dirty tree and names
datasets by their generate command and manifest sha256."""

import importlib.util
import json
import os
import re
import subprocess

import pytest

from envisat_pose.perception.weights import read_metadata, shipped_weights_path
from envisat_pose.provenance import find_absolute_paths, relative_name, scrub_paths

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

# written here independently of envisat_pose.provenance: a string that starts with "/" and has a second path
# component, or one that contains a usual root of a machine's files
PATH_START = re.compile(r"^/[\w.+~-]+/")
MACHINE_ROOTS = ("/tmp/", "/work/", "/home/", "/root/", "/Users/", "/mnt/", "/var/")


def strings(x):
    """Every string in a JSON value (keys and values), and each space-separated word of it."""
    if isinstance(x, str):
        yield x
        yield from x.split()
    elif isinstance(x, dict):
        for k, v in x.items():
            yield from strings(k)
            yield from strings(v)
    elif isinstance(x, list):
        for v in x:
            yield from strings(v)


def machine_paths(value) -> list[str]:
    return sorted({s for s in strings(value)
                   if PATH_START.match(s.strip("\"'(),;=")) or any(r in s for r in MACHINE_ROOTS)})


def test_no_absolute_path_in_the_card_or_the_weights_metadata():
    path = shipped_weights_path()
    card = json.load(open(os.path.join(os.path.dirname(path), "detector.json"), encoding="utf-8"))
    assert machine_paths(card) == []
    meta = read_metadata(path)
    decoded = {}
    for k, v in meta.items():  # metadata values are strings, most of them JSON
        try:
            decoded[k] = json.loads(v)
        except ValueError:
            decoded[k] = v
    assert machine_paths(decoded) == [] and machine_paths(meta) == []
    # the checker itself sees a path where there is one
    assert "/work/main/out/leg6/hseq633" in machine_paths({"data": "roi=labels; /work/main/out/leg6/hseq633"})
    assert "/srv/x/w.safetensors" in machine_paths(["--init /srv/x/w.safetensors"])


def test_the_card_names_its_data_and_its_code():
    card = json.load(open(os.path.join(os.path.dirname(shipped_weights_path()), "detector.json"), encoding="utf-8"))
    assert re.fullmatch(r"[0-9a-f]{40}", card["card_git"])
    for d in card["datasets"]:
        assert "path" not in d and d["name"]
        assert d["manifest_sha256"] is None or re.fullmatch(r"[0-9a-f]{64}", d["manifest_sha256"])
    assert all((r["command"].startswith("envisat train") or r.get("harness")) and r["git"]
               for r in card["training_runs"])


def test_paths_found_and_relative_names():
    text = "envisat train --data /tmp/dtrain --init /tmp/drun/checkpoint.safetensors; 5 px/s, 1/2 and/or"
    assert find_absolute_paths(text) == ["/tmp/dtrain", "/tmp/drun/checkpoint.safetensors"]
    assert scrub_paths(text) == "envisat train --data dtrain --init drun/checkpoint.safetensors; 5 px/s, 1/2 and/or"
    assert relative_name("/work/main/out/leg6/dcal") == "out/leg6/dcal"
    assert relative_name("/opt/a/b/c.json") == "b/c.json"
    assert relative_name("out/x") == "out/x"


def load_script():
    spec = importlib.util.spec_from_file_location("model_card", os.path.join(ROOT, "scripts", "model_card.py"))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_a_card_is_refused_from_a_dirty_tree(tmp_path):
    mc = load_script()
    git = ["git", "-c", "user.name=t", "-c", "user.email=t@t", "-c", "commit.gpgsign=false"]
    subprocess.run(["git", "init", "-q", str(tmp_path)], check=True)
    (tmp_path / "a.txt").write_text("one\n")
    subprocess.run(git + ["add", "a.txt"], cwd=tmp_path, check=True)
    subprocess.run(git + ["commit", "-q", "-m", "one"], cwd=tmp_path, check=True)
    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=tmp_path, capture_output=True, text=True).stdout.strip()
    assert mc.require_clean_tree(str(tmp_path)) == head
    (tmp_path / "a.txt").write_text("two\n")
    with pytest.raises(mc.Refused) as err:
        mc.require_clean_tree(str(tmp_path))
    assert "\n" not in str(err.value) and "uncommitted" in str(err.value) and "a.txt" in str(err.value)


def test_a_card_with_a_path_is_refused():
    mc = load_script()
    with pytest.raises(mc.Refused):
        mc.card_text({"commands": ["envisat calibrate --data /tmp/dcal"]})
    assert "dcal" in mc.card_text({"commands": ["envisat calibrate --data dcal"]})


def test_generate_command_from_a_manifest_config():
    from envisat_pose.config import to_dict
    from envisat_pose.datagen.factory import GenerateConfig

    mc = load_script()
    assert mc.generate_command(to_dict(GenerateConfig(num_images=300, seed=303)), "dcal") == \
        "envisat generate --num-images 300 --seed 303"
    assert mc.generate_command(to_dict(GenerateConfig(mode="sequence", scenario="slow-tumble", num_images=150,
                                                      seed=644)), "hseq644") == \
        "envisat generate --mode sequence --scenario slow-tumble --num-images 150 --seed 644"
    assert mc.generate_command(to_dict(GenerateConfig(num_images=100, seed=8282, earth_probability=1.0)), "e") == \
        "envisat generate --num-images 100 --seed 8282 --config CONFIG.toml  # CONFIG.toml: earth_probability = 1.0"
