"""The model card of a run stopped with Ctrl-C and resumed (the documented path for another target's detector):
its training time is the run's own clock over every leg, not the last leg's (config.json is rewritten by each
resume, so its mtime dated the last one), the resuming commands are listed, and an evaluation of `envisat
evaluate --target /abs/FILE.xml` leaves no machine path in the card (the card refused to be written)."""

import importlib.util
import json
import os

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def load_script():
    spec = importlib.util.spec_from_file_location("model_card", os.path.join(ROOT, "scripts", "model_card.py"))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


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
