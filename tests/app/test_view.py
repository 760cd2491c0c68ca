"""`envisat view`: which files it opens, the command lines it builds, and a real web viewer served on 127.0.0.1
only, answered and torn down (the whole process group). Rerun's settings go to temporary XDG folders with its
analytics switched off, so nothing is written to the home folder and nothing is sent anywhere."""

import os
import signal
import socket
import subprocess
import sys
import time
import urllib.request

import pytest

from envisat_pose.analysis import viewer as view
from envisat_pose.app.cli import main
from envisat_pose.config import InputError

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


@pytest.fixture()
def rerun_env(tmp_path, monkeypatch):
    """XDG folders under tmp_path with Rerun's analytics disabled there (`rerun analytics disable`)."""
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "xdg-config"))
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "xdg-data"))
    subprocess.run(view.rerun_command() + ["analytics", "disable"], check=True, capture_output=True, timeout=120)
    assert (tmp_path / "xdg-config" / "rerun" / "analytics.json").exists()
    return dict(os.environ)


def free_ports(n):
    socks = [socket.socket() for _ in range(n)]
    for s in socks:
        s.bind(("127.0.0.1", 0))
    ports = [s.getsockname()[1] for s in socks]
    for s in socks:
        s.close()
    return ports


def listeners(port):
    """Local addresses (hex, as in /proc/net/tcp*) that listen on `port`."""
    out = []
    for name in ("/proc/net/tcp", "/proc/net/tcp6"):
        if not os.path.exists(name):
            continue
        for line in open(name).read().splitlines()[1:]:
            f = line.split()
            addr, state = f[1], f[3]
            if state == "0A" and int(addr.split(":")[1], 16) == port:  # 0A: LISTEN
                out.append(addr.split(":")[0])
    return out


def wait_http(url, proc, deadline_s=120):
    """Poll until the URL answers 200 (or the process exits, or the deadline passes); returns the status."""
    end = time.monotonic() + deadline_s
    while time.monotonic() < end and proc.poll() is None:
        try:
            with urllib.request.urlopen(url, timeout=5) as r:
                return r.status
        except OSError:
            time.sleep(0.3)
    return None


def test_recordings_of_a_file_or_a_run_folder(tmp_path):
    (tmp_path / "b.rrd").write_bytes(b"x")
    (tmp_path / "a.rrd").write_bytes(b"x")
    assert view.recordings(str(tmp_path)) == [str(tmp_path / "a.rrd"), str(tmp_path / "b.rrd")]
    (tmp_path / "recording.rrd").write_bytes(b"x")
    assert view.recordings(str(tmp_path)) == [str(tmp_path / "recording.rrd")]
    assert view.recordings(str(tmp_path / "a.rrd")) == [str(tmp_path / "a.rrd")]
    for bad in (tmp_path / "nothing.rrd", tmp_path / "empty", tmp_path / "x.npz"):
        if bad.name == "empty":
            bad.mkdir()
        if bad.suffix == ".npz":
            bad.write_bytes(b"x")
        with pytest.raises(InputError):
            view.recordings(str(bad))
    adapted = tmp_path / "adapted"  # an adapt folder: its tracks' recordings one level down, named
    for sub in ("before", "after"):
        (adapted / sub).mkdir(parents=True)
        (adapted / sub / "recording.rrd").write_bytes(b"x")
    with pytest.raises(InputError, match=r"give one of its subfolders' \(.*after/recording.rrd, .*before/"):
        view.recordings(str(adapted))


def test_command_lines():
    native = view.viewer_command(["r.rrd"])
    assert native[-1] == "r.rrd" and "--serve-web" not in native
    web = view.viewer_command(["r.rrd"], web=True, port=1234, web_port=5678)
    assert web[-1] == "r.rrd"
    i = web.index("--bind")
    assert web[i + 1] == "127.0.0.1" and "0.0.0.0" not in web and "::" not in web
    assert web[web.index("--port") + 1] == "1234" and web[web.index("--web-viewer-port") + 1] == "5678"
    assert view.web_url(1234, 5678) == "http://127.0.0.1:5678/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A1234%2Fproxy"
    for port, web_port in ((0, 5678), (1234, 70000), (1234, 1234)):
        with pytest.raises(InputError):
            view.viewer_command(["r.rrd"], web=True, port=port, web_port=web_port)


def test_view_of_a_missing_file_is_one_error_line(tmp_path, capsys):
    assert main(["view", str(tmp_path / "nope.rrd")]) == 2
    assert "no such file" in capsys.readouterr().err


def test_view_refuses_a_file_that_is_not_a_recording_and_a_machine_without_a_display(tmp_path, capsys,
                                                                                    monkeypatch):
    """garbage.rrd (--web too: the old code served it, one core at 99 %) is one error line; without a display the
    native viewer is not started: exit 2 and the line says to use --web (the old code exited 0 after a
    window-system error)."""
    junk = tmp_path / "garbage.rrd"
    junk.write_bytes(b"this is not a recording" * 10)
    for extra in ([], ["--web"]):
        assert main(["view", str(junk), *extra]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "not a Rerun recording" in err, err
    rrd = tmp_path / "run.rrd"
    write_small_recording(rrd)
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr(sys, "platform", "linux")
    assert main(["view", str(rrd)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--web" in err and "display" in err, err
    # the native viewer's own server binds the loopback address too
    assert view.viewer_command([str(rrd)])[-3:] == ["--bind", "127.0.0.1", str(rrd)]


def test_view_refuses_a_recording_this_rerun_cannot_read_in_one_line(tmp_path, capsys):
    """A recording of another Rerun release whose encoding this one cannot read (its header's version set to
    0.22.0), or one cut short: one error line naming the rerun-sdk, exit 2, before any viewer starts (the old
    code served it: the viewer logged the error among its own lines and showed an empty recording). The file as
    written opens (Rerun's reader reads it: its chunks, the header's version this rerun-sdk's)."""
    import rerun as rr

    rrd = tmp_path / "run.rrd"
    write_small_recording(rrd)
    data = rrd.read_bytes()
    assert data[:4] == b"RRF2" and tuple(data[4:7]) == tuple(int(v) for v in rr.__version__.split(".")[:3])
    assert sum(1 for _ in rr.chunk.RrdReader(str(rrd)).stream()) > 0
    view.check_recording(str(rrd))  # no error
    older, cut = tmp_path / "older.rrd", tmp_path / "cut.rrd"
    older.write_bytes(data[:4] + bytes([0, 22, 0, 0]) + data[8:])
    cut.write_bytes(data[: len(data) // 2])
    for bad, words in ((older, "0.22.0"), (cut, "exceeds file size")):
        for extra in ([], ["--web"]):
            assert main(["view", str(bad), *extra]) == 2
            err = capsys.readouterr().err.strip()
            assert len(err.splitlines()) == 1, err
            assert f"cannot be read by rerun-sdk {rr.__version__}" in err and words in err, err


def test_a_port_in_use_is_one_error_line_naming_its_flag(tmp_path, capsys):
    """Something already listening on 127.0.0.1 at --web-port (another viewer, a killed one's orphan): one line
    naming the flag, before a viewer starts (once the line said 'serving ... open http://...' and the exit was
    0 while rerun failed to bind, or an orphan served its own recording at that address)."""
    import socket

    rrd = tmp_path / "run.rrd"
    write_small_recording(rrd)
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        taken = busy.getsockname()[1]
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:  # a port nothing holds, for --port
            probe.bind(("127.0.0.1", 0))
            free = probe.getsockname()[1]
        assert main(["view", str(rrd), "--web", "--port", str(free), "--web-port", str(taken)]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and f"--web-port {taken}" in err and "in use" in err, err


def write_small_recording(path):
    import numpy as np

    from envisat_pose.analysis.recording import write_estimates_recording
    from envisat_pose.contracts import Estimates

    T = 5
    x = np.zeros((1, T, 12))
    x[..., 1] = 50.0
    P = np.broadcast_to(np.eye(12) * 1e-4, (1, T, 12, 12)).copy()
    est = Estimates(t_s=np.arange(T, dtype=float), x_true=x, x_hat=x + 0.01, P=P, n_meas=np.zeros((1, T), int),
                    nis=np.zeros((1, T)), nis_dof=np.zeros((1, T), int), diverged=np.zeros(1, bool), config_json="{}")
    write_estimates_recording(str(path), est)


def test_web_viewer_serves_on_loopback_only_and_is_torn_down(tmp_path, rerun_env):
    rrd = tmp_path / "recording.rrd"
    write_small_recording(rrd)
    port, web_port = free_ports(2)
    proc = view.start_viewer(view.viewer_command(view.recordings(str(tmp_path)), web=True, port=port,
                                                 web_port=web_port), env=rerun_env, quiet=True)
    try:
        assert wait_http(f"http://127.0.0.1:{web_port}/", proc) == 200
        for p in (port, web_port):  # 127.0.0.1 is 0100007F in /proc/net/tcp
            assert listeners(p) and set(listeners(p)) == {"0100007F"}, (p, listeners(p))
    finally:
        view.stop_viewer(proc)
    with pytest.raises(ProcessLookupError):
        os.killpg(proc.pid, 0)  # nothing of the group is left
    assert listeners(port) == [] and listeners(web_port) == []


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_ctrl_c_stops_envisat_view_cleanly(tmp_path, rerun_env, sig):
    """`envisat view --web` in a terminal: Ctrl-C (SIGINT to envisat, not to the viewer's own group) or SIGTERM
    ends both."""
    rrd = tmp_path / "run.rrd"
    write_small_recording(rrd)
    port, web_port = free_ports(2)
    code = "import sys; from envisat_pose.app.cli import main; sys.exit(main(sys.argv[1:]))"
    proc = subprocess.Popen([sys.executable, "-c", code, "view", str(rrd), "--web", "--port", str(port),
                             "--web-port", str(web_port)], env=rerun_env, cwd=ROOT, start_new_session=True,
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        assert wait_http(f"http://127.0.0.1:{web_port}/", proc) == 200
        proc.send_signal(sig)
        out, _ = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 0
    assert view.web_url(port, web_port) in out
    assert listeners(port) == [] and listeners(web_port) == []
