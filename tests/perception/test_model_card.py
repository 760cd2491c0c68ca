"""The model card travels (issue 26, item 4): no absolute path of the machine that made it, in
models/detector.json, its history file or the shipped weights' metadata; scripts/model_card.py refuses a dirty
tree and names datasets by their generate command and manifest sha256. The card describes the weights beside it;
what was measured of earlier weights lives in models/detector_history.json (issue 39, item 7)."""

import importlib.util
import json
import os
import re
import shutil
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


def shipped_card(name: str = "detector.json") -> dict:
    return json.load(open(os.path.join(os.path.dirname(shipped_weights_path()), name), encoding="utf-8"))


def test_no_absolute_path_in_the_card_or_the_weights_metadata():
    path = shipped_weights_path()
    assert machine_paths(shipped_card()) == []
    assert machine_paths(json.load(open(os.path.join(ROOT, "models", "detector_history.json"), encoding="utf-8"))) == []
    # every committed card and its weights (another target's legs too: models/upper_stage_detector.*)
    cards = [os.path.join(ROOT, "models", f) for f in os.listdir(os.path.join(ROOT, "models"))
             if f.endswith("detector.json")]
    for card in cards:
        assert machine_paths(json.load(open(card, encoding="utf-8"))) == [], card
    for weights in [path] + [c[:-len(".json")] + ".safetensors" for c in cards]:
        meta = read_metadata(weights)
        decoded = {}
        for k, v in meta.items():  # metadata values are strings, most of them JSON
            try:
                decoded[k] = json.loads(v)
            except ValueError:
                decoded[k] = v
        assert machine_paths(decoded) == [] and machine_paths(meta) == [], weights
    # the checker itself sees a path where there is one
    assert "/work/main/out/leg6/hseq633" in machine_paths({"data": "roi=labels; /work/main/out/leg6/hseq633"})
    assert "/srv/x/w.safetensors" in machine_paths(["--init /srv/x/w.safetensors"])


def test_the_card_names_its_data_and_its_code():
    card = shipped_card()
    assert re.fullmatch(r"[0-9a-f]{40}", card["card_git"])
    for d in card["datasets"]:
        assert "path" not in d and d["name"]
        assert d["manifest_sha256"] is None or re.fullmatch(r"[0-9a-f]{64}", d["manifest_sha256"])
    assert all((r["command"].startswith("envisat train") or r.get("harness")) and r["git"]
               for r in card["training_runs"])


def test_the_card_holds_the_current_weights_and_names_its_history():
    card = shipped_card()
    assert "previous_weights" not in card and card["previous_weights_file"] == "detector_history.json"
    with open(os.path.join(ROOT, "models", card["previous_weights_file"]), encoding="utf-8") as fh:
        history = json.load(fh)
    shas = [p["sha256"] for p in history["previous_weights"]]
    assert shas and all(re.fullmatch(r"[0-9a-f]{64}", s) for s in shas) and len(set(shas)) == len(shas)
    assert card["weights"]["sha256"] not in shas
    assert all(set(p) == {"sha256", "evaluations", "error_model_measurements"} for p in history["previous_weights"])


def test_new_weights_retire_the_old_ones_into_the_history():
    mc = load_script()
    card = {"weights": {"sha256": "a" * 64, "tensors_sha256": "b" * 64}, "evaluations": {"e": 1},
            "error_model_measurements": {"m": 2}, "previous_weights": [{"sha256": "0" * 64}], "card_git": "x"}
    before = json.dumps(card)
    # the same tensors, only the calibration rewritten: the evaluations stay; an inline history leaves the card
    same, hist = mc.retire_weights(card, [], {"sha256": "c" * 64, "tensors_sha256": "b" * 64})
    assert same["evaluations"] == {"e": 1} and hist == [{"sha256": "0" * 64}]
    assert "previous_weights" not in same and same["previous_weights_file"] == mc.HISTORY_FILE
    # other tensors: the old weights' measurements move, under their sha256, after the earlier history
    new, hist = mc.retire_weights(card, [{"sha256": "f" * 64}], {"sha256": "d" * 64, "tensors_sha256": "e" * 64})
    assert [p["sha256"] for p in hist] == ["f" * 64, "0" * 64, "a" * 64]
    assert hist[-1] == {"sha256": "a" * 64, "evaluations": {"e": 1}, "error_model_measurements": {"m": 2}}
    assert "evaluations" not in new and new["weights"]["sha256"] == "d" * 64 and list(new)[0] == "weights"
    assert json.dumps(card) == before  # the caller's card untouched
    # no history yet: none named
    fresh, hist = mc.retire_weights({"weights": {"sha256": "a" * 64}}, [], {"sha256": "a" * 64, "tensors_sha256": ""})
    assert hist == [] and "previous_weights_file" not in fresh


def test_the_history_file_round_trips(tmp_path):
    mc = load_script()
    card = tmp_path / "detector.json"
    assert mc.history_path(str(card)) == str(tmp_path / mc.HISTORY_FILE) and mc.read_history(str(card) + "x") == []
    (tmp_path / mc.HISTORY_FILE).write_text(mc.history_text([{"sha256": "a" * 64, "evaluations": {}}]))
    assert mc.read_history(mc.history_path(str(card))) == [{"sha256": "a" * 64, "evaluations": {}}]
    with pytest.raises(mc.Refused):
        mc.history_text([{"sha256": "a" * 64, "evaluations": {"e": {"data": "/tmp/dcal"}}}])


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


@pytest.mark.skipif(shutil.which("git") is None, reason="no git on PATH")
def test_a_card_is_refused_from_a_dirty_tree(tmp_path, monkeypatch):
    mc = load_script()
    # the machine's own git settings (a global hooksPath whose hook refuses the commit, a signing key, templates)
    # are not this test's: a git of no global or system configuration
    monkeypatch.setenv("GIT_CONFIG_GLOBAL", os.devnull)
    monkeypatch.setenv("GIT_CONFIG_NOSYSTEM", "1")
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


def test_a_card_without_git_or_outside_a_checkout_is_refused_in_one_line(tmp_path, monkeypatch):
    """No git on PATH, or a folder that is not a git checkout: Refused in one line (a FileNotFoundError or
    CalledProcessError traceback before), nothing written."""
    mc = load_script()
    monkeypatch.setenv("GIT_CEILING_DIRECTORIES", str(tmp_path.parent))  # no checkout above tmp_path is found
    if shutil.which("git") is not None:
        with pytest.raises(mc.Refused, match="not a git checkout") as err:
            mc.require_clean_tree(str(tmp_path))
        assert "\n" not in str(err.value)
    monkeypatch.setenv("PATH", str(tmp_path))  # nothing named git there
    with pytest.raises(mc.Refused, match="no git on PATH"):
        mc.require_clean_tree(str(tmp_path))
    assert os.listdir(tmp_path) == []


def test_a_card_with_a_path_is_refused():
    mc = load_script()
    with pytest.raises(mc.Refused):
        mc.card_text({"commands": ["envisat calibrate --data /tmp/dcal"]})
    assert "dcal" in mc.card_text({"commands": ["envisat calibrate --data dcal"]})


def test_generate_command_from_a_manifest_config():
    from envisat_pose.config import to_dict
    from envisat_pose.datagen.generate_config import GenerateConfig, SequenceModeConfig

    mc = load_script()
    assert mc.generate_command(to_dict(GenerateConfig(num_images=300, seed=303)), "dcal") == \
        "envisat generate --num-images 300 --seed 303"
    assert mc.generate_command(to_dict(GenerateConfig(mode="sequence", sequence=SequenceModeConfig("slow-tumble"),
                                                      num_images=150, seed=644)), "hseq644") == \
        "envisat generate --mode sequence --scenario slow-tumble --num-images 150 --seed 644"
    assert mc.generate_command(to_dict(GenerateConfig(num_images=100, seed=8282, earth_probability=1.0)), "e") == \
        "envisat generate --num-images 100 --seed 8282 --config CONFIG.toml  # CONFIG.toml: earth_probability = 1.0"



# The model card of a run stopped with Ctrl-C and resumed (the documented path for another target's detector): its
# training time is the run's own clock over every leg, not the last leg's (config.json is rewritten by each resume,
# so its mtime dated the last one), the resuming commands are listed, and an evaluation of `envisat evaluate
# --target /abs/FILE.xml` leaves no machine path in the card (the card refused to be written).


def test_a_resumed_runs_card_counts_every_leg_and_lists_the_resumes(tmp_path):
    mc = load_script()
    run = tmp_path / "run"
    run.mkdir()
    resumes = [{"command": "envisat train --resume --out run", "git": "abc", "step": 44},
               {"command": "envisat train --resume --out run --time-budget-s 240", "git": "abc", "step": 81}]
    (run / "config.json").write_text(json.dumps({"train": {"steps": 20000}, "command": "envisat train --target "
                                                 "sat.xml --out run --time-budget-s 60", "resumes": resumes}))
    (run / "state.json").write_text(json.dumps({"step": 750, "epoch": 0, "batch": 0, "time_s": 296.5}))
    (run / "metrics.jsonl").write_text(json.dumps({"kind": "end", "loss": 2.4}) + "\n")
    (run / "checkpoint.safetensors").write_bytes(b"")
    t = os.path.getmtime(run / "checkpoint.safetensors")
    os.utime(run / "config.json", (t - 234.3, t - 234.3))  # the last leg's start: its resume rewrote config.json
    rec = mc.run_record(str(run))
    assert rec["wall_time_s"] == 296.5
    assert [r["command"] for r in rec["resumes"]] == [r["command"] for r in resumes]
    assert [r["step"] for r in rec["resumes"]] == [44, 81]


def test_an_evaluation_of_a_target_given_by_absolute_path_leaves_no_machine_path(tmp_path):
    mc = load_script()
    scores = {"all": {"pck_5px": 0.5}, "per_keypoint": {}, "pose": {"solved_share": 1.0}}
    e = {"weights": "/tmp/somewhere/run/checkpoint.safetensors", "data": "/tmp/somewhere/held_out", "frames": 3,
         "target": {"file": "/home/user/sats/sat.xml", "name": "sat", "sha256": "0" * 64}, "match_px": 5.0,
         "as_named": scores, "twin_aware": None}
    rec = mc.evaluation_record(e)
    assert rec["target"]["name"] == "sat" and rec["target"]["file"].endswith("sat.xml")
    mc.card_text({"evaluations": {"held_out": rec}})  # Refused while a machine path is left
