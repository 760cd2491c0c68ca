"""Output folders alike in every verb that writes (issue 41): --out (or the verb's output file flag) on or under
an existing file is one line naming it, exit 2, before any work; missing parent folders are made (the README's
`--out out/mc`, `--out data/train` in a fresh folder); a rerun says what it did."""

import os

import pytest

from envisat_pose.app.cli import main


@pytest.fixture()
def blocker(tmp_path, monkeypatch):
    """A fresh working folder holding one file, 'taken'."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "taken").write_text("a file, not a folder\n")
    return "taken"


UNDER = os.path.join("taken", "sub")
# every writing verb (train has its own tests) with its output under the file 'taken'; the inputs are valid
# enough to reach the output check, none of them needs to exist
CASES = {
    "generate": ["generate", "--num-images", "2", "--shard-size", "2", "--resolution", "64", "--out", UNDER],
    "dataset inspect --montage": ["dataset", "inspect", ".", "--montage", os.path.join(UNDER, "m.png")],
    "montecarlo": ["montecarlo", "--scenario", "default", "--runs", "2", "--duration-s", "10", "--out", UNDER],
    "montecarlo --rrd": ["montecarlo", "--scenario", "default", "--runs", "2", "--duration-s", "10", "--out", "mc",
                         "--rrd", os.path.join(UNDER, "r.rrd")],
    "estimate": ["estimate", "--scenario", "default", "--duration-s", "10", "--out", os.path.join(UNDER, "e.npz")],
    "simulate": ["simulate", "--duration-s", "10", "--out", os.path.join(UNDER, "run.npz")],
    "simulate --rrd": ["simulate", "--duration-s", "10", "--out", "run.npz", "--rrd", os.path.join(UNDER, "t.rrd")],
    "detect": ["detect", "--data", "ds", "--out", os.path.join(UNDER, "det.npz")],
    "calibrate": ["calibrate", "--data", "ds", "--out", os.path.join(UNDER, "c.safetensors")],
    "evaluate": ["evaluate", "--data", "ds", "--json", os.path.join(UNDER, "e.json")],
    "track": ["track", "--images", "frames", "--out", UNDER],
    "run": ["run", "--scenario", "default", "--duration-s", "10", "--out", UNDER],
    "demo": ["demo", "--duration-s", "10", "--out", UNDER],
    "report": ["report", "mc", "--out", os.path.join(UNDER, "r.html")],
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_an_output_under_a_file_is_one_line(case, blocker, tmp_path, capsys):
    assert main(CASES[case] + ["--quiet"] * (case not in ("dataset inspect --montage", "report"))) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "'taken' is a file, not a folder" in err, err
    assert sorted(os.listdir(tmp_path)) == ["taken"], "nothing written"


@pytest.mark.parametrize("args", [["generate", "--out", "taken"], ["track", "--images", "frames", "--out", "taken"],
                                  ["run", "--scenario", "default", "--out", "taken"]])
def test_an_output_folder_on_a_file_is_one_line(args, blocker, capsys):
    assert main(args + ["--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--out 'taken': exists and is not a folder" in err, err


def test_generate_makes_its_parents_and_a_rerun_says_it_had_nothing_to_do(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    args = ["generate", "--num-images", "3", "--shard-size", "2", "--resolution", "64", "--out",
            os.path.join("data", "train"), "--quiet"]
    assert main(args) == 0
    assert "wrote 3 images in 2 shards" in capsys.readouterr().out
    shard = tmp_path / "data" / "train" / "shard-000001.tar"
    before = shard.stat().st_mtime_ns
    assert main(args) == 0
    assert capsys.readouterr().out.strip() == \
        f"nothing to do: 3 images already there in 2 shards in {os.path.join('data', 'train')}"
    assert shard.stat().st_mtime_ns == before
    os.remove(shard)  # a shard lost: the rerun redoes it and says so
    assert main(args) == 0
    assert "wrote 1 image in 1 shard to data/train; 2 images already there" in capsys.readouterr().out


def test_file_outputs_make_their_parents(tmp_path, monkeypatch):
    """simulate's --out and --rrd (estimate's go through the same app.view.prepare_output_files)."""
    monkeypatch.chdir(tmp_path)
    run, rrd = os.path.join("runs", "truth", "run.npz"), os.path.join("rec", "s", "t.rrd")
    assert main(["simulate", "--duration-s", "6", "--out", run, "--rrd", rrd, "--quiet"]) == 0
    assert (tmp_path / run).is_file() and (tmp_path / "runs" / "truth" / "run.config.toml").is_file()
    assert (tmp_path / rrd).is_file()


def test_montecarlo_makes_its_parents(tmp_path, monkeypatch, capsys):
    """The README's `envisat montecarlo ... --out out/mc` in a fresh folder; then the report beside it."""
    monkeypatch.chdir(tmp_path)
    args = ["montecarlo", "--scenario", "default", "--runs", "4", "--duration-s", "20", "--settle-s", "10",
            "--block-runs", "2", "--out", os.path.join("out", "mc"), "--quiet"]
    assert main(args) == 0
    assert capsys.readouterr().out.startswith(f"wrote {os.path.join('out', 'mc')}: 4 runs")
    assert main(["report", os.path.join("out", "mc"), "--out", os.path.join("out", "reports", "r.html")]) == 0
    assert (tmp_path / "out" / "reports" / "r.html").is_file()
