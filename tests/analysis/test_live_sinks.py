"""A recording streamed to a live viewer: a viewer that cannot be reached is refused before any work, and one that
never takes the recording ends the job with a warning, not a wait (Rerun's own flush waits forever there, deaf to
Ctrl-C)."""

import socket
import subprocess
import sys
import textwrap

import pytest

from envisat_pose.analysis.sink_check import check_sink, viewer_address
from envisat_pose.config import InputError


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_connect_to_a_port_where_no_viewer_listens_is_refused_naming_it():
    port = _free_port()
    with pytest.raises(InputError, match=f"no Rerun viewer is listening at 127.0.0.1:{port}"):
        check_sink(f"connect:rerun+http://127.0.0.1:{port}/proxy")


def test_connect_to_a_listening_port_passes():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        assert check_sink(f"connect:rerun+http://127.0.0.1:{port}/proxy")[0] == "connect"


def test_spawn_without_a_display_is_refused(monkeypatch):
    monkeypatch.setattr(sys, "platform", "linux")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    with pytest.raises(InputError, match="no display"):
        check_sink("spawn")


def test_viewer_addresses_in_the_forms_users_write_them():
    assert viewer_address("rerun+http://127.0.0.1:9877/proxy") == ("127.0.0.1", 9877)
    assert viewer_address("localhost:9000") == ("localhost", 9000)
    assert viewer_address("rerun+http://10.0.0.2/proxy") == ("10.0.0.2", 9876)
    with pytest.raises(InputError, match="expected rerun\\+http://HOST:PORT/proxy"):
        viewer_address("rerun+http://:99999/proxy")


@pytest.mark.slow
def test_a_viewer_gone_before_the_recorder_connects_ends_in_a_warning_not_a_hang():
    # a viewer listens when the job is checked, then is closed before the recorder connects (modelled by skipping
    # the recorder's own check): nothing ever takes the recording
    script = textwrap.dedent("""
        import socket
        import time
        import numpy as np
        from envisat_pose.analysis import recording_stream
        from envisat_pose.geometry import load_camera
        viewer = socket.socket()
        viewer.bind(("127.0.0.1", 0))
        viewer.listen()
        url = "rerun+http://127.0.0.1:%d/proxy" % viewer.getsockname()[1]
        recording_stream.check_sink("connect:" + url)
        viewer.close()
        recording_stream.check_sink = lambda sink: sink.partition(":")
        recording_stream.LIVE_FLUSH_TIMEOUT_S = 1.0
        rec = recording_stream.TrackRecorder("connect:" + url, load_camera(), with_truth=False)
        image = np.zeros((512, 512), np.uint8)
        # frames over longer than Rerun tries to connect (~6 s), more than its queue holds: its flush never returned
        for k in range(200):
            rec.rec.set_time("frame", sequence=k)
            rec.rec.log("world/chaser/camera/image", recording_stream.rr.Image(image))
            time.sleep(0.05)
        rec.close()
        print("closed")
    """)
    # the subprocess's timeout is the hang's witness: with Rerun's unbounded flush it never returns
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=90)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "closed" in out.stdout
    assert "did not take all of it within 1 s" in out.stderr
