"""`envisat generate` and `envisat dataset verify` agree on a dataset folder: a stray shard that verify reports is
refused by generate (not left behind under exit 0); a finished dataset on read-only media is 'nothing to do' with
nothing written, and a read-only folder holding a partial file says so; a damaged manifest is a problem verify finds
(exit 1), not a usage error; the end line counts '1 image in 1 shard'."""

import os
import shutil

import pytest

from envisat_pose.app.cli import main
from envisat_pose.app.generate import generate_line

FLAGS = ["--num-images", "2", "--shard-size", "1", "--resolution", "64", "--seed", "3", "--quiet"]


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    """A finished two-shard dataset (one 64 px image a shard), copied by each test that changes it."""
    out = str(tmp_path_factory.mktemp("gen") / "ds")
    assert main(["generate", *FLAGS, "--out", out]) == 0
    return out


def state(folder):
    """Each entry's (name, inode, mtime): what a run that writes nothing leaves as it was."""
    return sorted((e.name, e.inode(), e.stat().st_mtime_ns) for e in os.scandir(folder))


def test_a_stray_shard_verify_reports_is_refused_by_generate_not_kept_under_exit_0(finished, tmp_path, capsys):
    out = str(tmp_path / "ds")
    shutil.copytree(finished, out)
    shutil.copy(os.path.join(out, "shard-000001.tar"), os.path.join(out, "shard-000004.tar"))  # beyond num_shards 2
    assert main(["dataset", "verify", out]) == 1
    assert "shard-000004.tar: not part of the dataset" in capsys.readouterr().out
    before = state(out)
    assert main(["generate", *FLAGS, "--out", out]) == 2
    err = capsys.readouterr().err
    assert "shard-000004.tar" in err and "none of its 2" in err and len(err.strip().splitlines()) == 1, err
    assert state(out) == before  # refused before anything was written; the user's file is theirs to move
    os.remove(os.path.join(out, "shard-000004.tar"))
    assert main(["generate", *FLAGS, "--out", out]) == 0
    assert main(["dataset", "verify", out]) == 0


def test_a_finished_dataset_on_read_only_media_is_nothing_to_do_and_nothing_is_written(finished, tmp_path,
                                                                                          monkeypatch, capsys):
    """Read-only media: the folder refuses every write (os.access says so, root included on a read-only mount);
    root passes a chmod, so the test makes os.access say what a read-only mount would."""
    out = str(tmp_path / "ds")
    shutil.copytree(finished, out)
    real_access = os.access

    def read_only(path, mode, *args, **kwargs):
        if mode & os.W_OK and os.path.realpath(path).startswith(os.path.realpath(out)):
            return False
        return real_access(path, mode, *args, **kwargs)

    monkeypatch.setattr(os, "access", read_only)
    before = state(out)
    os.chmod(out, 0o555)
    try:
        rc = main(["generate", *FLAGS, "--out", out])
    finally:
        os.chmod(out, 0o755)
    captured = capsys.readouterr()
    assert rc == 0 and captured.out.startswith("nothing to do: 2 images already there in 2 shards"), captured
    assert state(out) == before  # no lock file, no manifest or config rewritten
    assert main(["generate", "--num-images", "3", *FLAGS[2:], "--out", out]) == 2  # another config: still refused
    assert "another config or seed" in capsys.readouterr().err


@pytest.mark.parametrize("unfinished", [True, False])
def test_a_read_only_folder_with_a_partial_file_says_what_is_there_in_one_line(finished, tmp_path, monkeypatch,
                                                                                capsys, unfinished):
    """An interrupted run's partial file in a read-only dataset folder (beside 1 of 2 shards, or beside all): once
    the general 'cannot write there'; now the finished shards, the partial file and the folder's being read-only,
    nothing written. The writable folder's rerun removes the partial file (and finishes the dataset)."""
    import json

    out = str(tmp_path / "ds")
    shutil.copytree(finished, out)
    partial = ".tmp-999999999-shard-000001.tar-x1y2"  # a writer long gone (no such pid)
    if unfinished:
        with open(os.path.join(out, "manifest.json")) as fh:
            manifest = json.load(fh)
        manifest.update(shards=manifest["shards"][:1], complete=False)
        with open(os.path.join(out, "manifest.json"), "w") as fh:
            json.dump(manifest, fh)
        os.rename(os.path.join(out, "shard-000001.tar"), os.path.join(out, partial))
    else:
        with open(os.path.join(out, partial), "wb") as fh:
            fh.write(b"half a shard")
    real_access = os.access

    def read_only(path, mode, *args, **kwargs):  # a read-only mount (module's test above: root passes a chmod)
        if mode & os.W_OK and os.path.realpath(path).startswith(os.path.realpath(out)):
            return False
        return real_access(path, mode, *args, **kwargs)

    monkeypatch.setattr(os, "access", read_only)
    before = state(out)
    capsys.readouterr()
    assert main(["generate", *FLAGS, "--out", out]) == 2
    err = capsys.readouterr().err
    held = "1 of the dataset's 2 shards finished" if unfinished else "the dataset's 2 shards, all finished"
    assert len(err.strip().splitlines()) == 1 and "is read-only" in err and held in err, err
    assert f"{partial} (a partial file an interrupted run left" in err, err
    assert ("cannot finish it there" if unfinished else "cannot remove it there") in err, err
    assert state(out) == before  # no lock file, nothing removed or rewritten
    monkeypatch.undo()
    assert main(["generate", *FLAGS, "--out", out]) == 0
    assert main(["dataset", "verify", out]) == 0 and not os.path.exists(os.path.join(out, partial))


@pytest.mark.parametrize("text, problem", [
    ("{", "unreadable manifest.json"),
    ("[1]", "manifest.json holds a JSON list"),
    ('{"shards": 3}', "expected a list 'shards'"),
    ('{"shards": [], "num_shards": "x"}', "num_shards = 'x': expected a non-negative integer"),
    ('{"shards": [], "num_shards": null}', "num_shards = None: expected a non-negative integer"),
])
def test_verify_finds_a_damaged_manifest_a_problem_exit_1(tmp_path, capsys, text, problem):
    (tmp_path / "manifest.json").write_text(text)
    (tmp_path / "shard-000000.tar").write_bytes(b"")
    assert main(["dataset", "verify", str(tmp_path)]) == 1
    out = capsys.readouterr().out
    assert out.startswith("PROBLEM ") and problem in out and f"{tmp_path}: 1 problem" in out, out


def test_verify_of_a_folder_that_is_no_dataset_is_still_a_usage_error(tmp_path, capsys):
    assert main(["dataset", "verify", str(tmp_path / "nowhere")]) == 2
    assert "no such folder" in capsys.readouterr().err
    assert main(["dataset", "verify", str(tmp_path)]) == 2  # no manifest: not a dataset
    assert "no manifest.json" in capsys.readouterr().err


def test_the_end_line_counts_one_image_in_one_shard():
    entry = {"count": 1}
    one = {"shards": [entry]}
    assert generate_line(one, [entry], "d").startswith("wrote 1 image in 1 shard to d (")
    assert generate_line(one, [], "d") == "nothing to do: 1 image already there in 1 shard in d"
    two = {"shards": [{"count": 2}, entry]}
    assert generate_line(two, [entry], "d").startswith("wrote 1 image in 1 shard to d; 2 images already there (")
    assert generate_line({"shards": [{"count": 2}] * 2}, [], "d") == "nothing to do: 4 images already there in 2 shards in d"
