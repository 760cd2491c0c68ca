"""Peak memory of `envisat run` against its length: the default scenario at a small resolution for 1, 3 and 10
orbits of the default orbit (period ~6000 s), one run, cold start, each job a fresh `envisat run` process.

Measured per job: the process's peak resident set (getrusage's ru_maxrss of the child, from os.wait4), its increase
over a short baseline job of the same settings (BASE_S of simulated time: what the process needs whatever the
run's length: Python, torch, MuJoCo, the detector, Rerun), the job's wall time and frames. Beside it the peer:
the bytes that holding every frame would take, frames x the per-frame arrays a run records
(closed_loop.record_arrays, ~2 kB a frame; before the streaming rewrite a run held those whole, returned them
through the runner and the job stacked them again for est.npz).

At 1 Hz a frame costs ~0.1 s here (128 px; the detector dominates), so 10 orbits is 60000 frames and ~100 min:
--rate-hz takes fewer frames per orbit (the report says what ran), --orbits fewer orbits. Fresh processes differ
by tens of MiB in peak RSS (a 301-frame job peaked 5 MiB below the 21-frame baseline), and lit frames grow the
peak by more than the arrays (measured in one process at 128 px: +10 MiB over 600 lit frames with the Rerun
recording, +0 without it): what grows is outside the run's arrays.

Run: .venv/bin/python bench/memory.py [--orbits 1 3 10] [--rate-hz 1] [--resolution 128]
     [--out bench/results/memory.json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
BASE_S = 20.0  # the baseline job's simulated time, s


def envisat_exe() -> list[str]:
    """The `envisat` entry point next to this Python (the venv's), else `python -m envisat_pose.app.cli`."""
    exe = os.path.join(os.path.dirname(sys.executable), "envisat")
    return [exe] if os.path.isfile(exe) else [sys.executable, "-m", "envisat_pose.app.cli"]


def run_job(duration_s: float, config: str, out_dir: str) -> dict:
    """One `envisat run` in its own process: peak RSS (MiB), wall time (s), and its summary's frames/timing."""
    cmd = envisat_exe() + ["run", "--scenario", "default", "--duration-s", str(duration_s), "--config", config,
                           "--out", out_dir, "--quiet"]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    _, status, usage = os.wait4(proc.pid, 0)
    wall_s = time.perf_counter() - t0
    err = proc.stderr.read()
    proc.stderr.close()
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        raise SystemExit(f"envisat run failed ({proc.returncode}): {err[-2000:]}")
    with open(os.path.join(out_dir, "summary.json")) as fh:
        summary = json.load(fh)
    return {"duration_s": duration_s, "frames": summary["frames"], "peak_rss_mib": usage.ru_maxrss / 1024,
            "wall_s": wall_s, "ms_per_frame": 1000 * summary["wall_s"]["loops"] / summary["frames"],
            "frames_skipped_eclipse": summary["run0"]["frames_skipped_eclipse"],
            "est_npz_bytes": os.path.getsize(os.path.join(out_dir, "est.npz")),
            "det_npz_bytes": os.path.getsize(os.path.join(out_dir, "det.npz"))}


def frame_bytes() -> int:
    """Bytes of one frame of the arrays a run records (closed_loop.record_arrays)."""
    from envisat_pose.pipelines.closed_loop import record_arrays

    return sum(a.nbytes for a in record_arrays(1).values())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--orbits", type=float, nargs="+", default=[1, 3, 10])
    ap.add_argument("--rate-hz", type=float, default=1.0, help="camera and filter rate (frames per second)")
    ap.add_argument("--resolution", type=int, default=128, help="image side, px")
    ap.add_argument("--out", default=os.path.join(ROOT, "bench", "results", "memory.json"))
    args = ap.parse_args(argv)
    from envisat_pose.datagen.scenario import scenario_config

    period_s = scenario_config("default").orbit.period_s
    per_frame = frame_bytes()
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench-memory-") as tmp:
        config = os.path.join(tmp, "run.toml")
        with open(config, "w") as fh:
            fh.write(f"rate_hz = {args.rate_hz}\n[image]\nresolution_px = {args.resolution}\n")
        jobs = [("baseline", BASE_S)] + [(f"{o:g} orbit(s)", o * period_s) for o in args.orbits]
        for name, duration_s in jobs:
            row = {"job": name} | run_job(duration_s, config, os.path.join(tmp, name.replace(" ", "_")))
            row["every_frame_mib"] = row["frames"] * per_frame / 2**20
            rows.append(row)
            print(f"{name:>12}: {row['frames']:6d} frames, peak RSS {row['peak_rss_mib']:7.1f} MiB, "
                  f"wall {row['wall_s']:7.1f} s", flush=True)
    base = rows[0]["peak_rss_mib"]
    for row in rows:
        row["peak_over_baseline_mib"] = row["peak_rss_mib"] - base
    print(f"\nenvisat run, default scenario, {args.resolution} px, {args.rate_hz:g} Hz, one run, cold start "
          f"(orbit period {period_s:.0f} s; every frame = frames x {per_frame} B of per-frame arrays)")
    print(f"{'job':>12} {'frames':>7} {'peak RSS MiB':>13} {'over baseline':>14} {'every frame MiB':>16} "
          f"{'ms/frame':>9} {'wall s':>8}")
    for r in rows:
        print(f"{r['job']:>12} {r['frames']:7d} {r['peak_rss_mib']:13.1f} {r['peak_over_baseline_mib']:14.1f} "
              f"{r['every_frame_mib']:16.1f} {r['ms_per_frame']:9.1f} {r['wall_s']:8.1f}")
    result = {"scenario": "default", "resolution_px": args.resolution, "rate_hz": args.rate_hz,
              "orbit_period_s": period_s, "per_frame_bytes": per_frame, "jobs": rows,
              "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version()},
              "date": time.strftime("%Y-%m-%d")}
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as fh:
        json.dump(result, fh, indent=1)
        fh.write("\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
