"""`envisat montecarlo --out DIR` on a folder holding block files the campaign did not write: a block beyond its last,
a file named like a block that is none, a folder where a block goes, blocks beside no manifest (another campaign's,
copied in). Each is refused in one line naming the file and what was expected, with nothing written or removed (once
the first two were left beside the campaign under exit 0, the folder was a traceback, the copied-in blocks were
silently deleted); the campaign's own blocks still resume."""

import os
import shutil

import pytest

from envisat_pose.app.cli import main

BASE = ["montecarlo", "--scenario", "default", "--runs", "3", "--duration-s", "20", "--settle-s", "10",
        "--block-runs", "1", "--seed", "3", "--quiet"]
EXPECTED = "expected blocks/block-0000.npz to blocks/block-0002.npz"


@pytest.fixture(scope="module")
def campaigns(tmp_path_factory):
    """A finished three-block campaign (seed 3) and another campaign's (seed 4), copied by each test."""
    root = tmp_path_factory.mktemp("mc")
    assert main(BASE + ["--out", str(root / "a")]) == 0
    assert main(BASE[:-3] + ["--seed", "4", "--quiet", "--out", str(root / "b")]) == 0
    return root / "a", root / "b"


def state(folder):
    """Every entry's (path, inode, mtime), blocks/ included: what a run that writes nothing leaves as it was."""
    return sorted((os.path.relpath(os.path.join(d, n), folder), os.stat(os.path.join(d, n)).st_ino,
                   os.stat(os.path.join(d, n)).st_mtime_ns)
                  for d, dirs, files in os.walk(folder) for n in dirs + files)


def refused_line(out, capsys, *words):
    before = state(out)
    capsys.readouterr()
    assert main(BASE + ["--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and all(w in err for w in words), err
    assert state(out) == before  # nothing written, nothing removed
    return err


@pytest.mark.parametrize("name", ["block-0007.npz", "block-7.npz"])
def test_a_block_file_that_is_none_of_the_campaigns_is_refused_then_the_campaign_resumes(campaigns, tmp_path, capsys,
                                                                                         name):
    d = tmp_path / "c"
    shutil.copytree(campaigns[0], d)
    (d / "summary.json").unlink()  # an unfinished campaign: the rerun has work to do
    shutil.copy(campaigns[1] / "blocks" / "block-0001.npz", d / "blocks" / name)
    refused_line(d, capsys, os.path.join("blocks", name), "none of its 3", EXPECTED)
    os.remove(d / "blocks" / name)
    kept = (d / "blocks" / "block-0001.npz").stat().st_mtime_ns
    assert main(BASE + ["--out", str(d)]) == 0
    assert (d / "summary.json").read_bytes() == (campaigns[0] / "summary.json").read_bytes()
    assert (d / "blocks" / "block-0001.npz").stat().st_mtime_ns == kept  # its own block resumed, not redone


def test_a_folder_where_a_block_goes_is_refused_in_one_line(campaigns, tmp_path, capsys):
    d = tmp_path / "c"
    shutil.copytree(campaigns[0], d)
    (d / "blocks" / "block-0001.npz").unlink()
    (d / "blocks" / "block-0001.npz").mkdir()
    (d / "blocks" / "block-0001.npz" / "notes.txt").write_text("a user's")
    refused_line(d, capsys, os.path.join("blocks", "block-0001.npz"), "a folder", "expected a file it wrote")


def test_blocks_beside_no_manifest_are_another_campaigns_refused_not_removed(campaigns, tmp_path, capsys):
    """A campaign writes its manifest before its first block: blocks in a folder without one were copied in."""
    d = tmp_path / "c"
    (d / "blocks").mkdir(parents=True)
    shutil.copy(campaigns[0] / "truth.npz", d / "truth.npz")
    shutil.copy(campaigns[1] / "blocks" / "block-0000.npz", d / "blocks" / "block-0000.npz")
    refused_line(d, capsys, os.path.join("blocks", "block-0000.npz"), "no manifest.json")


def test_a_sweeps_later_rate_folder_of_other_files_is_refused_before_any_rate_runs(tmp_path, capsys):
    """A rate's folder its campaign refuses (here files of another job, no manifest) was found only when that rate's
    turn came, after the slower rates' campaigns had run; now one line before any of them."""
    d = tmp_path / "sweep"
    (d / "rate-1hz").mkdir(parents=True)
    (d / "rate-1hz" / "notes.txt").write_text("a user's")
    argv = BASE[:3] + ["--runs", "2", "--duration-s", "20", "--settle-s", "10", "--rates-hz", "1", "0.5", "--quiet"]
    assert main(argv + ["--out", str(d)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and os.path.join("sweep", "rate-1hz") in err[0] and "notes.txt" in err[0], err
    assert sorted(os.listdir(d)) == ["rate-1hz"]  # the 0.5 Hz campaign, run first, never started
