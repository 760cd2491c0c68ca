"""`envisat view FILE_OR_RUN_DIR`: open a Rerun recording (`.rrd`) in the viewer, or serve the web viewer
(analysis/viewer.py: the recordings, the command line, the process group). Ctrl-C here ends the viewer's whole
group cleanly; without a display (Linux: neither DISPLAY nor WAYLAND_DISPLAY set) the native viewer is not started:
the error says to use --web.

Rerun keeps its analytics settings under $XDG_CONFIG_HOME/rerun and $XDG_DATA_HOME/rerun (default: the home
folder); `rerun analytics disable` switches them off.
"""

from __future__ import annotations

import argparse
import signal
import sys

from envisat_pose.analysis.viewer import (
    BIND,
    DEFAULT_PORT,
    DEFAULT_WEB_PORT,
    check_ports_free,
    check_recording,
    has_display,
    recordings,
    start_viewer,
    stop_viewer,
    viewer_command,
    web_url,
)
from envisat_pose.config import InputError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "view",
        help="open a Rerun recording (.rrd, or a run folder) in the viewer; --web serves it on 127.0.0.1",
        description="Open a recording written by --rrd (or the recording.rrd / .rrd files of a run folder) in the "
        "Rerun viewer. With --web, serve the web viewer on 127.0.0.1 only and print its address; Ctrl-C stops it.",
    )
    p.add_argument("path", metavar="FILE_OR_RUN_DIR",
                   help="a .rrd file, or a folder holding recording.rrd or .rrd files")
    p.add_argument("--web", action="store_true", help="serve the web viewer on 127.0.0.1 instead of the native viewer")
    p.add_argument("--port", type=int, default=DEFAULT_PORT, help=f"with --web: gRPC port (default {DEFAULT_PORT})")
    p.add_argument("--web-port", type=int, default=DEFAULT_WEB_PORT,
                   help=f"with --web: HTTP port of the web viewer (default {DEFAULT_WEB_PORT})")
    p.set_defaults(func=run_view, flag_names={"port": "--port", "web_port": "--web-port"})


def _interrupt(signum, frame):
    raise KeyboardInterrupt


def run_view(args: argparse.Namespace) -> int:
    files = recordings(args.path)
    for f in files:
        check_recording(f)
    if not args.web and not has_display():
        raise InputError("no display to open a viewer window on (DISPLAY and WAYLAND_DISPLAY are unset): use "
                         f"`envisat view {args.path} --web` and open the address it prints in a browser")
    cmd = viewer_command(files, web=args.web, port=args.port, web_port=args.web_port)
    if args.web:
        check_ports_free(args.port, args.web_port)
    # Ctrl-C and SIGTERM end the viewer's group too, even where SIGINT came in ignored (a job started with `&`)
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, _interrupt)
    proc = start_viewer(cmd)
    if args.web:
        print(f"serving {', '.join(files)} on {BIND} only: open {web_url(args.port, args.web_port)} "
              "(Ctrl-C to stop)", flush=True)
    try:
        code = proc.wait()
    except KeyboardInterrupt:
        stop_viewer(proc)
        print("envisat view: stopped", file=sys.stderr)
        return 0
    if code != 0 and not args.web:
        print(f"envisat view: error: the viewer exited with code {code} (no window could be opened?): use --web",
              file=sys.stderr)
    return code
