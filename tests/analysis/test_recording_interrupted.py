"""A recording written whole from arrays (`--rrd` of simulate, estimate, montecarlo, dataset inspect) stopped while
its file is flushed (Ctrl-C, or the OS refusing the bytes): the stop goes on, and the file is not put in place (it
was renamed to its path, its writer unfinished, while the verb said 'interrupted')."""

import errno
import os

import pytest
import rerun as rr

import envisat_pose.analysis.recording_writers as writers
from envisat_pose.analysis.recording_layout import truth_blueprint


def write(path: str) -> None:
    """What every array writer does: its series logged inside _Recording (write_truth_recording's form)."""
    with writers._Recording(path, truth_blueprint()) as rec:
        rec.log("metrics/x", rr.Scalars(1.0))


@pytest.mark.parametrize("stop", [KeyboardInterrupt(), OSError(errno.ENOSPC, "No space left on device")])
def test_a_recording_stopped_in_its_flush_leaves_no_file(tmp_path, monkeypatch, stop):
    def stopped(rec, tmp):
        raise stop

    monkeypatch.setattr(writers, "flush_file", stopped)
    path = tmp_path / "truth.rrd"
    with pytest.raises(type(stop)):
        write(str(path))
    assert os.listdir(tmp_path) == []  # neither the file nor its temporary


def test_a_recording_not_stopped_is_put_in_place(tmp_path):
    path = tmp_path / "truth.rrd"
    write(str(path))
    assert os.listdir(tmp_path) == ["truth.rrd"] and path.stat().st_size > 0
