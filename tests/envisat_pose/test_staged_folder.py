"""io.staged_folder: a job's outputs staged in a hidden folder and moved into place whole; the staging folder a
killed job left (SIGKILL: no clean-up ran) is swept by the next job, a running job's and other names are kept."""

import os
import subprocess
import sys

import pytest

from envisat_pose.io import STAGE_PREFIX, stage_prefix, staged_folder


def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def test_a_killed_jobs_stage_is_swept_and_a_running_ones_kept(tmp_path):
    out = tmp_path / "out"
    killed = out / f"{STAGE_PREFIX}{_dead_pid()}-abc"
    running = out / f"{stage_prefix()}xyz"  # this process: alive
    other = out / f"{STAGE_PREFIX}notapid"
    for folder in (killed, running, other):
        (folder / "runs").mkdir(parents=True)
        (folder / "runs" / "rows.bin").write_bytes(b"half written")
    (out / "notes.txt").write_text("the user's own file")
    with staged_folder(str(out), ("summary.json",)) as stage:
        assert os.path.basename(stage).startswith(stage_prefix())
        with open(os.path.join(stage, "summary.json"), "w") as fh:
            fh.write("{}")
    assert sorted(os.listdir(out)) == sorted([running.name, other.name, "notes.txt", "summary.json"])


def test_a_finished_job_removes_its_earlier_outputs_it_did_not_write_again(tmp_path):
    """An earlier run's det.npz (this run writes none: another mode) would describe other frames beside the new
    summary: a finished job removes the outputs it names and did not write, and keeps every other file."""
    out = tmp_path / "out"
    out.mkdir()
    for name, text in (("summary.json", "earlier"), ("det.npz", "earlier"), ("notes.txt", "the user's own")):
        (out / name).write_text(text)
    with staged_folder(str(out), ("summary.json", "det.npz")) as stage:
        with open(os.path.join(stage, "summary.json"), "w") as fh:
            fh.write("new")
    assert sorted(os.listdir(out)) == ["notes.txt", "summary.json"]
    assert (out / "summary.json").read_text() == "new" and (out / "notes.txt").read_text() == "the user's own"


def test_an_error_leaves_the_earlier_outputs(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "summary.json").write_text("earlier")
    with pytest.raises(RuntimeError):
        with staged_folder(str(out), ("summary.json",)) as stage:
            with open(os.path.join(stage, "summary.json"), "w") as fh:
                fh.write("half")
            raise RuntimeError("killed")
    assert os.listdir(out) == ["summary.json"] and (out / "summary.json").read_text() == "earlier"


def test_a_killed_exports_stage_beside_its_folder_is_swept(tmp_path):
    """dataset export stages its folder beside out_dir (.tmp-export-PID-NAME-...): a killed export's is swept by
    the next export into that parent, a running one's kept."""
    from envisat_pose.pipelines.datasets.export import STAGE_PREFIX as EXPORT_PREFIX
    from envisat_pose.pipelines.datasets.export import _make_stage

    killed = tmp_path / f"{EXPORT_PREFIX}{_dead_pid()}-coco-abc"
    running = tmp_path / f"{stage_prefix(EXPORT_PREFIX)}coco-xyz"
    for folder in (killed, running):
        (folder / "images").mkdir(parents=True)
    stage, made = _make_stage(str(tmp_path / "coco"))
    assert made == [] and os.path.basename(stage).startswith(stage_prefix(EXPORT_PREFIX) + "coco-")
    assert sorted(os.listdir(tmp_path)) == sorted([running.name, os.path.basename(stage)])
