"""Peak memory of `envisat run` against its length: the default scenario at a small resolution for 1, 3 and 10
orbits of the default orbit (period ~6000 s), one run, cold start, each job a fresh `envisat run` process.

Measured per job: the process's peak resident set (getrusage's ru_maxrss of the child, from os.wait4), its increase
over a short baseline job of the same settings (BASE_FRAMES frames, at any rate: what the process needs whatever
the run's length: Python, torch, MuJoCo, the detector, Rerun), the job's wall time and frames, and inside the loop the
process's resident set every --trace-every frames (the child runs `envisat run`'s job in-process,
pipelines.jobs.resolve_job then run_closed_loop, with the tracker's step wrapped to read /proc/self/statm: Linux): its
growth from the first sample to the last, per 1000 frames and per 1000 lit frames (frames with an image; in the
Earth's shadow a frame is only the filter's prediction). That in-loop slope is what tells growth apart; fresh processes' peaks differ by tens of MiB (a
301-frame job peaked 5 MiB below the 21-frame baseline). Beside it the peer: the bytes that holding every frame
would take, frames x the per-frame arrays a run records (rows.record_arrays, ~2 kB a frame).

Found with it: the loop grew 45-70 MiB per 1000 lit frames, all in run 0's Rerun recording (in one
process at 128 px over 800 lit frames: +45 MiB with the recording, +4 without it, +3 with the recorder only
setting times). Rerun's file sink keeps ~2 kB of metadata per chunk for the .rrd's footer until the file closes,
and the default batcher cut ~23 chunks a frame (one per entity at every 200 ms flush, at ~0.1 s a frame).
analysis.recording.TrackRecorder now writes its file in chunks of FILE_CHUNK_ROWS rows without a footer. At 1 Hz,
--orbits 0.1 0.3, before -> after: the 0.3-orbit loop grew 68.6 -> 5.5 MiB from frame 200 to 1800 (1003 lit), its
peak over the baseline 146.5 -> 14.5 MiB, its recording 41.3 -> 4.0 MB; what is left is the first ~1000 frames'
warm-up (a 0.62-orbit job then grew 1.4 MiB over 2600 frames, through the shadow and out of it).

At 1 Hz a lit frame costs ~0.09 s here (128 px; the detector dominates; a frame in the shadow ~5 ms; 65 % of the
default orbit is lit), so 10 orbits is 60068 frames (39046 lit) and the jobs at 1, 3 and 10 orbits take ~80 min:
--rate-hz takes fewer frames per orbit (the report says what ran; at 0.5 Hz 10 orbits is 30034 frames and the
three jobs ~40 min), --orbits fewer orbits. (At 0.25 and 0.2 Hz the tracker's cold start once gated out every
corner of its window and started tracking with a zero covariance; a fit without a positive-definite covariance now
starts nothing and acquisition goes on: at 0.2 Hz the default scenario converged 95 s after its first frame.)

Run: .venv/bin/python bench/memory.py [--orbits 1 3 10] [--rate-hz 1] [--resolution 128] [--trace-every 200]
     [--out bench/results/memory.json]
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
import tempfile
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
BASE_FRAMES = 21  # the baseline job's frames (20 s at 1 Hz)


# the child: the job of `envisat run --scenario default --duration-s D --config C --out O` (the pipeline the verb
# calls, resolved as the verb resolves it: pipelines.jobs.resolve_job) in this Python, Tracker.step wrapped to sample the resident set every
# BENCH_TRACE_EVERY frames
CHILD = """
import json, os, sys
from envisat_pose.pipelines.tracking import tracker

every, rows, n = int(os.environ["BENCH_TRACE_EVERY"]), [], {"frames": 0, "lit": 0}
page_mib = os.sysconf("SC_PAGE_SIZE") / 2**20
step = tracker.Tracker.step


def traced(self, t_s, image, *args, **kwargs):  # Tracker.step's own arguments, whatever they grow to
    out = step(self, t_s, image, *args, **kwargs)
    n["frames"] += 1
    n["lit"] += image is not None
    if n["frames"] % every == 0:
        with open("/proc/self/statm") as fh:
            rows.append([n["frames"], n["lit"], int(fh.read().split()[1]) * page_mib])
    return out


tracker.Tracker.step = traced
from envisat_pose.pipelines.jobs import resolve_job
from envisat_pose.pipelines.runs.closed_loop import run_closed_loop

duration_s, config, out_dir = float(sys.argv[1]), sys.argv[2], sys.argv[3]
run_closed_loop(resolve_job("run", "default", config, duration_s=duration_s), out_dir, progress=False)
with open(os.environ["BENCH_TRACE"], "w") as fh:
    json.dump(rows, fh)
"""


def run_job(duration_s: float, config: str, out_dir: str, trace_every: int) -> dict:
    """One `envisat run` in its own process: peak RSS (MiB), wall time (s), its summary's frames/timing, and the
    loop's RSS trace (frames, lit frames, MiB) every trace_every frames."""
    trace = out_dir + ".trace.json"
    cmd = [sys.executable, "-c", CHILD, str(duration_s), config, out_dir]
    env = os.environ | {"BENCH_TRACE": trace, "BENCH_TRACE_EVERY": str(trace_every)}
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env)
    err = proc.stderr.read()  # read before waiting: a full pipe would block the child
    proc.stderr.close()
    _, status, usage = os.wait4(proc.pid, 0)
    wall_s = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        raise SystemExit(f"the run job failed ({proc.returncode}): {err[-2000:]}")
    with open(os.path.join(out_dir, "summary.json")) as fh:
        summary = json.load(fh)
    with open(trace) as fh:
        rss = json.load(fh)
    skipped = summary["run0"]["frames_skipped_eclipse"]
    return {"duration_s": duration_s, "frames": summary["frames"], "lit_frames": summary["frames"] - skipped,
            "peak_rss_mib": usage.ru_maxrss / 1024, "wall_s": wall_s,
            "ms_per_frame": 1000 * summary["wall_s"]["loops"] / summary["frames"],
            "frames_skipped_eclipse": skipped, "recording_bytes": summary["recording_bytes"],
            "est_npz_bytes": os.path.getsize(os.path.join(out_dir, "est.npz")),
            "det_npz_bytes": os.path.getsize(os.path.join(out_dir, "det.npz"))} | loop_growth(rss) | {"rss_trace": rss}


def loop_growth(rss: list) -> dict:
    """The loop's RSS growth from its first sample (after trace_every frames; the first ~1000 frames still add ~5 MiB
    of warm-up) to its last: MiB, per 1000 frames and per 1000 lit frames (None with fewer than two samples)."""
    if len(rss) < 2:
        return {"loop_growth_mib": None, "loop_mib_per_1000_frames": None, "loop_mib_per_1000_lit_frames": None}
    (k0, l0, m0), (k1, l1, m1) = rss[0], rss[-1]
    return {"loop_growth_mib": m1 - m0, "loop_mib_per_1000_frames": 1000 * (m1 - m0) / (k1 - k0),
            "loop_mib_per_1000_lit_frames": 1000 * (m1 - m0) / (l1 - l0) if l1 > l0 else None}


def frame_bytes() -> int:
    """Bytes of one frame of the arrays a run records (rows.record_arrays)."""
    from envisat_pose.pipelines.runs.rows import record_arrays

    return sum(a.nbytes for a in record_arrays(1).values())


def main(argv=None) -> int:
    from _common import (  # bench/_common.py
        WholeFlagParser,
        count,
        description,
        out_file,
        positive,
        provenance,
        write_json,
    )

    ap = WholeFlagParser(description=description(__doc__))
    ap.add_argument("--orbits", type=positive, nargs="+", default=[1, 3, 10])
    ap.add_argument("--rate-hz", type=positive, default=1.0, help="camera and filter rate (frames per second)")
    ap.add_argument("--resolution", type=count(), default=128, help="image side, px")
    ap.add_argument("--trace-every", type=count(), default=200, help="frames between the loop's RSS samples")
    ap.add_argument("--seed", type=count(0), default=0, help="the run's seed (as `envisat run --seed`)")
    ap.add_argument("--out", type=out_file, default=os.path.join(ROOT, "bench", "results", "memory.json"))
    args = ap.parse_args(argv)
    from envisat_pose.datagen.scenario import scenario_config

    period_s = scenario_config("default").orbit.period_s
    per_frame = frame_bytes()
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench-memory-") as tmp:
        config = os.path.join(tmp, "run.toml")
        with open(config, "w") as fh:
            fh.write(f"rate_hz = {args.rate_hz}\nseed = {args.seed}\n[image]\nresolution_px = {args.resolution}\n")
        jobs = [("baseline", (BASE_FRAMES - 1) / args.rate_hz)]
        jobs += [(f"{o:g} orbit(s)", o * period_s) for o in args.orbits]
        for name, duration_s in jobs:
            row = {"job": name} | run_job(duration_s, config, os.path.join(tmp, name.replace(" ", "_")),
                                         args.trace_every)
            row["every_frame_mib"] = row["frames"] * per_frame / 2**20
            rows.append(row)
            print(f"{name:>12}: {row['frames']:6d} frames, peak RSS {row['peak_rss_mib']:7.1f} MiB, "
                  f"wall {row['wall_s']:7.1f} s", flush=True)
    base = rows[0]["peak_rss_mib"]
    for row in rows:
        row["peak_over_baseline_mib"] = row["peak_rss_mib"] - base
    print(f"\nenvisat run, default scenario, {args.resolution} px, {args.rate_hz:g} Hz, one run, cold start "
          f"(orbit period {period_s:.0f} s; every frame = frames x {per_frame} B of per-frame arrays)")
    print(f"{'job':>12} {'frames':>7} {'lit':>6} {'peak RSS MiB':>13} {'over baseline':>14} {'loop growth':>12} "
          f"{'MiB/1000 lit':>13} {'every frame MiB':>16} {'rrd MB':>7} {'ms/frame':>9} {'wall s':>8}")

    def num(v, fmt):
        return format("-", f">{fmt.split('.')[0]}") if v is None else format(v, fmt)

    for r in rows:
        print(f"{r['job']:>12} {r['frames']:7d} {r['lit_frames']:6d} {r['peak_rss_mib']:13.1f} "
              f"{r['peak_over_baseline_mib']:14.1f} {num(r['loop_growth_mib'], '12.1f')} "
              f"{num(r['loop_mib_per_1000_lit_frames'], '13.2f')} {r['every_frame_mib']:16.1f} "
              f"{r['recording_bytes'] / 1e6:7.1f} {r['ms_per_frame']:9.1f} {r['wall_s']:8.1f}")
    long = rows[1:]
    if len(long) >= 2:  # the peaks' slope over the jobs (fresh processes: tens of MiB of noise each)
        lit = np.array([r["lit_frames"] for r in long], float)
        peak = np.array([r["peak_rss_mib"] for r in long])
        if np.ptp(lit) > 0:
            slope = float(np.polyfit(lit, peak, 1)[0]) * 1000
            print(f"peak RSS against lit frames over the {len(long)} jobs: {slope:+.2f} MiB per 1000 lit frames")
    result = {"scenario": "default", "resolution_px": args.resolution, "rate_hz": args.rate_hz,
              "orbit_period_s": period_s, "per_frame_bytes": per_frame, "trace_every": args.trace_every, "jobs": rows,
              "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "python": platform.python_version()},
              "date": time.strftime("%Y-%m-%d")}
    result["provenance"] = provenance(args)
    write_json(args.out, result, indent=1)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    from _common import run_main  # bench/_common.py, beside this script

    run_main(main)
