"""`envisat train --resume` of another target's online run from a folder other than the one it started in: the
run keeps its target file as typed (relative), so it cannot be found from there. The one line says so and how to
go on; it blamed `--target = 'sat.xml'`, a flag the user had not typed."""

import json
import os

import pytest

from envisat_pose.app.cli import main
from envisat_pose.pipelines.detector.train_records import read_run_config


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


def _run_folder(tmp_path, target: str):
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text(json.dumps({"train": {"target": target, "steps": 10}}))
    (run / "state.json").write_text(json.dumps({"step": 5}))
    return run


class _Cfg:
    def __init__(self, target):
        self.target = target

    def to_dict(self):
        return {"target": self.target, "steps": 12}


def test_a_resume_naming_the_runs_own_file_by_another_path_goes_on(tmp_path, monkeypatch, capsys):
    """The run started with `--target sat.xml`; a resume typed with the same file's absolute path is the same
    target, not 'another config'; another file still is. From another folder (the kept relative path not found
    there) the resume is refused in one line whatever `--target` says: the run's renders record that path."""
    from envisat_pose.config import InputError
    from envisat_pose.perception.train_run import check_resume

    start, elsewhere = tmp_path / "start", tmp_path / "elsewhere"
    start.mkdir()
    elsewhere.mkdir()
    (start / "sat.xml").write_text("<mujoco/>")
    (start / "other.xml").write_text("<mujoco/>")
    run = _run_folder(start, "sat.xml")
    monkeypatch.chdir(start)
    check_resume(str(run), _Cfg(str(start / "sat.xml")), None)  # the same file, its absolute path
    with pytest.raises(InputError, match="another config: target 'sat.xml' -> 'other.xml'"):
        check_resume(str(run), _Cfg("other.xml"), None)
    monkeypatch.chdir(elsewhere)
    assert main(["train", "--resume", "--out", str(run), "--target", str(start / "sat.xml"), "--steps", "12",
                 "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "the folder the run started in" in err[0], err
