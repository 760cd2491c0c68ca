"""`envisat train --resume` of another target's online run from a folder other than the one it started in: the
run keeps its target file as typed (relative), so it cannot be found from there. The one line says so and how to
go on; it blamed `--target = 'sat.xml'`, a flag the user had not typed."""

import json
import os

from envisat_pose.app.cli import main
from envisat_pose.pipelines.detector.train import read_run_config


def test_a_resume_from_another_folder_says_where_to_resume_from(tmp_path, monkeypatch, capsys):
    start, elsewhere = tmp_path / "start", tmp_path / "elsewhere"
    start.mkdir()
    elsewhere.mkdir()
    (start / "sat.xml").write_text("<mujoco/>")
    run = start / "runs" / "sat"
    run.mkdir(parents=True)
    (run / "config.json").write_text(json.dumps({"train": {"target": "sat.xml", "steps": 10}}))
    (run / "state.json").write_text(json.dumps({"step": 5}))
    monkeypatch.chdir(start)
    assert read_run_config(os.path.join("runs", "sat"))["target"] == "sat.xml"  # found from where it started
    monkeypatch.chdir(elsewhere)
    assert main(["train", "--resume", "--out", str(run), "--steps", "12", "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "'sat.xml'" in err[0] and "the folder the run started in" in err[0], err
    assert sorted(os.listdir(run)) == ["config.json", "state.json"]
