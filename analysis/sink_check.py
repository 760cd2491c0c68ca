"""Where a recording goes (a light module: no rerun import), checked before a job makes anything: the sink's
spelling and, for a live viewer, that it can be reached (a spawned viewer needs a display; a `connect` URL a viewer
listening there). Without these checks a run with no viewer to take its recording finished its loop and then
waited for one forever, deaf to Ctrl-C (Rerun's flush holds the interpreter)."""

from __future__ import annotations

import os
import socket
import urllib.parse

from envisat_pose.analysis.viewer import DEFAULT_PORT, has_display
from envisat_pose.config import InputError

DEFAULT_CONNECT_URL = f"rerun+http://127.0.0.1:{DEFAULT_PORT}/proxy"  # Rerun's own default for connect_grpc
PROBE_TIMEOUT_S = 2.0  # a viewer on this machine or the LAN answers a TCP connect well within this


def check_sink(sink: str) -> tuple[str, str, str]:
    """A recording sink's (kind, ':', argument): InputError naming `sink` unless it is 'save:PATH', 'spawn' or
    'connect:URL' (a job checks it before any work); 'spawn' without a display and 'connect' with no viewer
    listening at the URL (or at Rerun's default, DEFAULT_CONNECT_URL, for 'connect:') are refused too."""
    kind, sep, arg = sink.partition(":") if isinstance(sink, str) else ("", "", "")
    if kind not in ("save", "spawn", "connect") or (kind == "save" and not arg):
        raise InputError(f"sink {sink!r}: expected 'save:PATH', 'spawn' or 'connect:URL'")
    if kind == "save":
        check_recording_path(arg, "sink")
    if kind == "spawn" and not has_display():
        raise InputError("sink 'spawn': no display to open a viewer window on (DISPLAY and WAYLAND_DISPLAY are "
                         "unset): record to the job's file instead (its recording.rrd) and serve it with "
                         "`envisat view OUT_DIR --web`")
    if kind == "connect":
        host, port = viewer_address(arg or DEFAULT_CONNECT_URL)
        if not listening(host, port):
            raise InputError(f"sink {sink!r}: no Rerun viewer is listening at {host}:{port}: start the viewer "
                             "first, or record to the job's file instead (its recording.rrd)")
    return kind, sep, arg


def check_recording_path(path: str, field: str) -> None:
    """InputError naming field unless the recording's path (a file, or the folder it goes in) is UTF-8, as a full
    path: Rerun's writer takes no other (a Latin-1 folder name was a UnicodeEncodeError traceback from inside it,
    after the job's work)."""
    try:
        os.path.abspath(path).encode("utf-8")
    except UnicodeEncodeError:
        raise InputError(f"{field} {path!r}: a path that is not UTF-8; expected a UTF-8 path (Rerun writes the "
                         "recording to no other): rename it") from None


def viewer_address(url: str) -> tuple[str, int]:
    """The (host, port) of a viewer's URL (rerun+http://HOST:PORT/proxy, http://..., or HOST:PORT); InputError
    naming the URL when it has neither."""
    parsed = urllib.parse.urlsplit(url if "//" in url else f"//{url}")
    try:
        host, port = parsed.hostname, parsed.port
    except ValueError:
        host, port = None, None
    if not host:
        raise InputError(f"viewer URL {url!r}: expected rerun+http://HOST:PORT/proxy")
    return host, port or DEFAULT_PORT


def listening(host: str, port: int, timeout_s: float = PROBE_TIMEOUT_S) -> bool:
    """Whether something accepts a TCP connection at host:port."""
    try:
        with socket.create_connection((host, port), timeout=timeout_s):
            return True
    except OSError:
        return False
