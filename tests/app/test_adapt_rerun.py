"""`envisat adapt` run again into the same --out: a rejected rerun leaves the earlier adopted detector.safetensors
and its card as they were (a rejected result loses nothing), says so in report.json and on stderr; an adopted
rerun replaces them. A folder adapt did not write (a user's own before/, report.json) and an --out on, in or
around the frames are refused in one line, their files intact. The job's own work (tracks, labels, fine-tune) is
stood in for; its files are the real ones (_finish)."""

import json
import os
import types

import numpy as np
import pytest

import envisat_pose.app.adapt as adapt_verb
import envisat_pose.pipelines.adaptation.adapt as adapt_module
from envisat_pose.app.cli import main


@pytest.fixture
def stand_in(monkeypatch, tmp_path):
    """The job stood in for: each run writes what _adapt writes, adopted or not as `verdict` says (the weights
    file's bytes name the run)."""
    (tmp_path / "frames").mkdir()
    frame = tmp_path / "frames" / "frame.png"
    frame.write_bytes(b"not read")
    source = types.SimpleNamespace(path=str(tmp_path / "frames"), kind="images", t_s=np.arange(4.0), size_px=(8, 8),
                                   bit_depth=8, files=[str(frame)], scenario=None)
    verdict = {"reason": None, "run": 0}

    def job(cfg, tcfg, source, camera, remap, stage, progress, command, *rest):
        verdict["run"] += 1
        if verdict["reason"] is None:
            with open(os.path.join(stage, "detector.safetensors"), "wb") as fh:
                fh.write(f"run {verdict['run']}".encode())
        figures = {"tracked_share": 1.0, "mean_nis_per_dof": 1.0, "stays_tracked_from": 2}
        return adapt_module._finish(cfg, tcfg, source, stage, command, figures, figures, [{"labels": 30}], {}, 0.0,
                                    verdict["reason"])

    monkeypatch.setattr(adapt_verb, "open_source", lambda *args: source)
    monkeypatch.setattr(adapt_module, "prepare_frames", lambda tcfg, src, camera: (tcfg, src, None, None, None))
    monkeypatch.setattr(adapt_module, "_adapt", job)
    return verdict


def run(out) -> int:
    return main(["adapt", "--images", "frames", "--out", str(out), "--quiet"])


def test_a_rejected_rerun_keeps_the_earlier_adopted_weights(stand_in, tmp_path, capsys):
    out = tmp_path / "run"
    assert run(out) == 0
    card = (out / "detector.json").read_text()
    stand_in["reason"] = "the adapted weights tracked fewer held-out frames"
    capsys.readouterr()
    assert run(out) == 1
    err = capsys.readouterr().err.strip()
    assert (out / "detector.safetensors").read_bytes() == b"run 1"  # once removed by the rejected rerun
    assert (out / "detector.json").read_text() == card
    report = json.loads((out / "report.json").read_text())
    assert report["adopted"] is False and report["earlier_weights_kept"] is True
    assert len(err.splitlines()) == 1 and "fewer held-out frames" in err, err
    assert f"earlier adopted {out / 'detector.safetensors'} stays" in err, err


def test_an_adopted_rerun_replaces_them_and_a_first_rejected_run_writes_none(stand_in, tmp_path, capsys):
    out = tmp_path / "run"
    assert run(out) == 0 and run(out) == 0
    assert (out / "detector.safetensors").read_bytes() == b"run 2"
    stand_in["reason"] = "nothing to adopt"
    fresh = tmp_path / "fresh"
    capsys.readouterr()
    assert run(fresh) == 1
    assert "stays" not in capsys.readouterr().err
    assert not (fresh / "detector.safetensors").exists() and not (fresh / "detector.json").exists()
    assert json.loads((fresh / "report.json").read_text())["earlier_weights_kept"] is False


@pytest.mark.parametrize("entry", ["before", "after", "report.json", "detector.json"])
def test_a_users_folder_of_an_outputs_name_is_refused_and_kept(stand_in, tmp_path, capsys, entry):
    out = tmp_path / "mine"
    mine = out / entry / "notes.txt" if entry in ("before", "after") else out / entry
    mine.parent.mkdir(parents=True)
    mine.write_text("the user's own\n")
    assert run(out) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and f"--out {str(out)!r} holds" in err and "no report.json" in err, err
    assert mine.read_text() == "the user's own\n" and stand_in["run"] == 0, "refused before any work"


def test_an_adapt_folder_whose_before_is_not_a_track_run_is_refused(stand_in, tmp_path, capsys):
    out = tmp_path / "run"
    stand_in["reason"] = "rejected"  # no before/ written by the stand-in: the user's goes in beside its report
    assert run(out) == 1
    (out / "before").mkdir()
    (out / "before" / "notes.txt").write_text("kept\n")
    capsys.readouterr()
    assert run(out) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "holds before/ without the track.config.toml" in err, err
    assert (out / "before" / "notes.txt").read_text() == "kept\n"


@pytest.mark.parametrize("where, how", [("frames", "is"), ("frames/run", "lies inside"), (".", "holds")])
def test_an_out_on_in_or_around_the_frames_is_refused(stand_in, tmp_path, capsys, monkeypatch, where, how):
    monkeypatch.chdir(tmp_path)
    assert run(where) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and f"--out {where!r} {how} --images {str(tmp_path / 'frames')!r}" in err, err
    assert os.listdir(tmp_path / "frames") == ["frame.png"] and stand_in["run"] == 0
