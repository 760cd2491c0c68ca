"""The Rerun viewer as a process (`envisat view`): which recordings a path names, the `rerun` command line of the
installed rerun-sdk (`python -m rerun_cli`, the release that wrote the file), and starting and stopping it in its
own process group (the command is a wrapper around a child binary, so the whole group is ended). Every server it
starts listens on 127.0.0.1 only: the native viewer's own gRPC server and, with web, the web viewer and its gRPC
proxy. A file that is not a Rerun recording (its first bytes are not an RRD stream header), or that this
rerun-sdk cannot read (another Rerun release's incompatible encoding, a file cut short), is refused in one line.
"""

from __future__ import annotations

import glob
import os
import signal
import subprocess
import sys
import time
import urllib.parse

from envisat_pose.config import InputError

BIND = "127.0.0.1"
DEFAULT_PORT = 9876  # Rerun's gRPC proxy
DEFAULT_WEB_PORT = 9090  # Rerun's web viewer over HTTP
RUN_DIR_RECORDING = "recording.rrd"  # the recording a run folder holds
RRD_MAGIC = b"RRF"  # an RRD stream's first bytes (b"RRF2" for the current encoding)


def recordings(path: str) -> list[str]:
    """The .rrd files to open: the file itself, or a folder's recording.rrd, else every .rrd in it (sorted)."""
    if os.path.isdir(path):
        main = os.path.join(path, RUN_DIR_RECORDING)
        if os.path.isfile(main):
            return [main]
        found = sorted(glob.glob(os.path.join(glob.escape(path), "*.rrd")))
        if not found:
            below = sorted(glob.glob(os.path.join(glob.escape(path), "*", "*.rrd")))  # an adapt folder's rounds
            hint = f": give one of its subfolders' ({', '.join(below[:4])}{', ...' if len(below) > 4 else ''})" \
                if below else ""
            raise InputError(f"{path!r}: no {RUN_DIR_RECORDING} and no .rrd file in this folder{hint}")
        return found
    if not os.path.isfile(path):
        raise InputError(f"{path!r}: no such file or folder")
    if not path.endswith(".rrd"):
        raise InputError(f"{path!r}: expected a Rerun recording (.rrd) or a run folder")
    return [path]


def check_recording(path: str) -> None:
    """InputError (one line) when the file does not start like a Rerun recording."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(len(RRD_MAGIC) + 1)
    except OSError as err:
        raise InputError(f"{path!r}: cannot be read ({err.strerror or err})") from None
    if not head.startswith(RRD_MAGIC):
        raise InputError(f"{path!r}: not a Rerun recording (no RRD header; expected a .rrd written by envisat "
                         "--rrd, run, track or demo)")
    check_decodable(path)


def check_decodable(path: str) -> None:
    """InputError (one line) when this environment's rerun-sdk, the viewer's release, cannot read the file: one
    written by an incompatible Rerun release, or cut short (its last message incomplete). The viewer itself
    would log the error among its own lines and serve an empty or partial recording. Rerun's reader reads the
    footer's index, or for a file without one (an older TrackRecorder's) steps over the messages' headers (0.2 s
    for 200 MiB), and decodes the first chunk."""
    import warnings

    import rerun as rr

    with warnings.catch_warnings():  # a file without a footer is read whole, as the viewer does: not an error
        warnings.simplefilter("ignore")
        try:
            reader = rr.chunk.RrdReader(str(path))
            reader.recordings()  # the index: a file cut short fails here
            next(iter(reader.stream()), None)  # the first chunk decoded: another release's encoding fails here
        except (RuntimeError, OSError, ValueError) as err:
            why = " ".join(str(err).split())
            raise InputError(f"{path!r}: cannot be read by rerun-sdk {rr.__version__} (the viewer `envisat view` "
                             f"starts): {why}") from None


def has_display() -> bool:
    """Whether a native window can be opened: on Linux a DISPLAY or WAYLAND_DISPLAY is set; elsewhere assumed."""
    if not sys.platform.startswith("linux"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def rerun_command() -> list[str]:
    """The `rerun` command of this environment's rerun-sdk."""
    return [sys.executable, "-m", "rerun_cli"]


def viewer_executable() -> str | None:
    """The `rerun` executable installed beside this Python (a virtual environment's bin folder, found whether or
    not it is on PATH); None: Rerun searches PATH."""
    path = os.path.join(os.path.dirname(sys.executable), "rerun")
    return path if os.access(path, os.X_OK) else None


def viewer_command(files: list[str], web: bool = False, port: int = DEFAULT_PORT,
                   web_port: int = DEFAULT_WEB_PORT) -> list[str]:
    """The command line: `rerun --bind 127.0.0.1 FILE...`, or with web `rerun --serve-web --bind 127.0.0.1 --port P
    --web-viewer-port W FILE...` (never another address)."""
    if not web:
        return rerun_command() + ["--bind", BIND, *files]
    for name, value in (("port", port), ("web_port", web_port)):
        if not 1 <= value <= 65535:
            raise InputError(f"{name} {value}: expected a port from 1 to 65535")
    if port == web_port:
        raise InputError(f"port and `web_port` are both {port}: expected two different ports")
    return rerun_command() + ["--serve-web", "--bind", BIND, "--port", str(port), "--web-viewer-port", str(web_port),
                              *files]


def check_ports_free(port: int, web_port: int) -> None:
    """InputError naming the port when something on this machine already listens on BIND at it (another viewer, a
    killed one's orphan): the web viewer would fail to start there, or a page would show another recording."""
    import socket

    for name, value in (("port", port), ("web_port", web_port)):
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # a closed connection's TIME_WAIT is no owner
            try:
                s.bind((BIND, value))
            except OSError:
                raise InputError(f"{name} {value}: {BIND}:{value} is in use (another viewer, or one left running?): "
                                 "stop it or give another port") from None


def web_url(port: int, web_port: int) -> str:
    """The address of the web viewer, pointed at the gRPC proxy that serves the recording."""
    proxy = urllib.parse.quote(f"rerun+http://{BIND}:{port}/proxy", safe="")
    return f"http://{BIND}:{web_port}/?url={proxy}"


def start_viewer(cmd: list[str], env: dict | None = None, quiet: bool = False) -> subprocess.Popen:
    """Start the viewer in its own process group (a new session: Ctrl-C in the terminal does not reach it)."""
    out = subprocess.DEVNULL if quiet else None
    return subprocess.Popen(cmd, env=env, start_new_session=True, stdin=subprocess.DEVNULL, stdout=out, stderr=out)


def stop_viewer(proc: subprocess.Popen, wait_s: float = 10.0) -> int:
    """End the viewer's whole process group: SIGINT, then SIGTERM, then SIGKILL if it lingers; returns its code once
    no process of the group is left (a killed grandchild is reaped by init a moment after the wrapper exits: on a
    loaded machine the group was still there when this returned), or after wait_s more."""
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGKILL):
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            break
        try:
            proc.wait(timeout=wait_s)
            break
        except subprocess.TimeoutExpired:
            continue
    try:  # the wrapper may be gone while its child still runs
        os.killpg(proc.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    code = proc.wait()
    deadline = time.monotonic() + wait_s
    while time.monotonic() < deadline:
        try:
            os.killpg(proc.pid, 0)
        except ProcessLookupError:
            break
        time.sleep(0.05)
    return code
