"""A verb writes only among its own outputs: `track` and `run` refuse an --out holding files of their outputs'
names that no earlier run of theirs wrote (a user's summary.json, est.npz: no track.config.toml / run.config.toml
written by the verb), and `track` an --out on, inside or around its frames' folder; each in one line, before any
work, the user's files intact. An earlier run's folder is theirs to replace (out_dirs.refuse_foreign_outputs)."""

import os

import pytest

from envisat_pose.app.cli import main
from envisat_pose.config import InputError
from envisat_pose.out_dirs import refuse_foreign_outputs, refuse_overlap


@pytest.fixture
def frames(tmp_path, monkeypatch):
    """A working folder with frames/ of three image files (never decoded: every refusal comes first)."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "frames").mkdir()
    for k in range(3):
        (tmp_path / "frames" / f"f{k}.png").write_bytes(b"not read")
    return tmp_path / "frames"


def track(out: str) -> list[str]:
    return ["track", "--images", "frames", "--rate-hz", "1", "--out", out, "--quiet"]


@pytest.mark.parametrize("verb, name", [("track", "summary.json"), ("track", "est.npz"), ("run", "summary.json"),
                                        ("run", "truth.npz")])
def test_a_users_file_of_an_outputs_name_is_refused_and_kept(frames, tmp_path, capsys, verb, name):
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / name).write_text("the user's own\n")
    args = track("mine") if verb == "track" else ["run", "--duration-s", "10", "--out", "mine", "--quiet"]
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and f"--out 'mine' holds {name} but no {verb}.config.toml" in err, err
    assert (tmp_path / "mine" / name).read_text() == "the user's own\n"
    assert sorted(os.listdir(tmp_path / "mine")) == [name], "nothing written"


@pytest.mark.parametrize("out, how", [("frames", "is"), (os.path.join("frames", "run"), "lies inside"),
                                      (".", "holds")])
def test_a_track_out_on_in_or_around_the_frames_is_refused(frames, capsys, out, how):
    assert main(track(out)) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and f"--out {out!r} {how} --images 'frames'" in err, err
    assert sorted(os.listdir(frames)) == ["f0.png", "f1.png", "f2.png"]


def test_an_earlier_runs_folder_is_the_jobs_to_replace(tmp_path):
    out = tmp_path / "run"
    out.mkdir()
    (out / "summary.json").write_text("{}\n")
    (out / "track.config.toml").write_text("# envisat track: the full validated config of this job\n")
    refuse_foreign_outputs(str(out), ["summary.json", "track.config.toml"], "track.config.toml", "track")
    (out / "est.npz").mkdir()
    with pytest.raises(InputError, match="holds a folder 'est.npz' where the job's file est.npz goes"):
        refuse_foreign_outputs(str(out), ["est.npz"], "track.config.toml", "track")
    refuse_overlap(str(out), str(tmp_path / "elsewhere"))  # no such folder, and apart: nothing to refuse
    refuse_overlap(str(tmp_path / "runs"), str(tmp_path / "run"))  # a shared prefix is no overlap


@pytest.mark.parametrize("args", [["evaluate", "--data", "ds", "--json", os.path.join("ds", "manifest.json")],
                                  ["detect", "--data", "ds", "--out", os.path.join("ds", "det.npz")],
                                  ["calibrate", "--data", "ds", "--out", os.path.join("ds", "w.safetensors")]])
def test_an_output_file_inside_the_data_folder_is_refused(tmp_path, monkeypatch, capsys, args):
    """`evaluate --json ds/manifest.json` once replaced the dataset's manifest it had just read."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "ds").mkdir()
    (tmp_path / "ds" / "manifest.json").write_text("the dataset's\n")
    assert main(args + ["--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and f"{args[3]} {args[4]!r} lies inside --data 'ds'" in err, err
    assert os.listdir(tmp_path / "ds") == ["manifest.json"]
    assert (tmp_path / "ds" / "manifest.json").read_text() == "the dataset's\n"
