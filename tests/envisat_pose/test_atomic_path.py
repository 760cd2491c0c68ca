"""io.atomic_path: a file is written under a temporary name and renamed whole; the temporary file a writer killed
mid-write left (SIGKILL: no clean-up ran, e.g. a half-written `--rrd` recording) is swept by the next write of the
same path, a running writer's and other names are kept."""

import os
import signal
import subprocess
import sys
import textwrap

from envisat_pose.io import atomic_path, atomic_write_text


def test_a_writer_killed_mid_write_leaves_a_partial_that_the_next_write_sweeps(tmp_path):
    path = tmp_path / "track.rrd"
    code = textwrap.dedent(f"""
        import os, signal
        from envisat_pose.io import atomic_path
        with atomic_path({str(path)!r}) as tmp:
            open(tmp, "wb").write(b"half a recording")
            os.kill(os.getpid(), signal.SIGKILL)
    """)
    proc = subprocess.run([sys.executable, "-c", code], env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)})
    assert proc.returncode == -signal.SIGKILL
    left = [n for n in os.listdir(tmp_path) if n != "user.txt"]
    assert len(left) == 1 and left[0].startswith(".tmp-") and not path.exists(), left
    (tmp_path / "user.txt").write_text("the user's own file")
    mine = tmp_path / f".tmp-{os.getpid()}-track.rrd-running.rrd"  # a live writer's (this process)
    mine.write_bytes(b"still being written")
    atomic_write_text(str(path), "whole")
    assert path.read_text() == "whole"
    assert sorted(os.listdir(tmp_path)) == sorted([mine.name, "track.rrd", "user.txt"])


def test_a_failed_write_leaves_nothing(tmp_path):
    path = tmp_path / "a.png"
    try:
        with atomic_path(str(path)) as tmp:
            open(tmp, "wb").write(b"x")
            raise RuntimeError("the writer failed")
    except RuntimeError:
        pass
    assert os.listdir(tmp_path) == []
