"""Bounded memory: a long closed loop does not hold its frames. A run of 21000 frames (10 Hz, 64 px, the chaser in
the Earth's shadow all along, so it is quick) against a short one, in a fresh process: the job's peak memory
(every Python and numpy allocation, tracemalloc) grows by less than the per-frame arrays the run records would
take if held once (rows.record_arrays, ~2 kB a frame: ~40 MiB here; measured 29 MiB: the truth's
simulation, errors.png's 7200 frames, a few scalars a frame). Before the streaming rewrite a run held them whole,
the job stacked x_hat and P again and held the truth twice: more than 3.5 kB a frame. The peak resident set is
printed, not asserted (+0.6 MiB here before the recorder's fix below, +0.0 after).

Lit frames grew the resident set too, ~45-70 MiB per 1000 (bench/memory.py), outside the traced allocations: Rerun's
file sink keeps ~2 kB per chunk for the .rrd's footer, and the recorder's default batching cut ~23 chunks a frame
at ~0.1 s a frame. The shadowed frames above are too quick to show it (a few ms each: one chunk per entity for
~40 frames) and lit ones too slow for a test, so the second test checks the cause: the run's recording is cut into
chunks of FILE_CHUNK_ROWS frames however slowly they come; its footer then lists ~100x fewer chunks."""

import json
import subprocess
import sys
import textwrap
import time
import warnings
from collections import defaultdict

import numpy as np

CHILD = textwrap.dedent("""
    import json, resource, sys, tracemalloc
    import numpy as np
    from envisat_pose.pipelines.jobs import resolve_job
    from envisat_pose.datagen.orbit import chaser_orbit
    from envisat_pose.datagen.scenario import scenario_config
    from envisat_pose.pipelines.runs import closed_loop as loop

    weights, out, long_s = sys.argv[1], sys.argv[2], float(sys.argv[3])
    # the sun behind the Earth as seen from the chaser at t = 1050 s: the shadow covers ~0..2100 s
    r_mid = chaser_orbit(scenario_config("default").orbit, np.array([1050.0])).r_N_m[0]

    def cfg(duration_s):
        return resolve_job("run", "default", overrides={
            "duration_s": duration_s, "rate_hz": 10.0, "weights": weights, "workers": 1, "image.resolution_px": 64,
            "image.sun_dir": (-r_mid / np.linalg.norm(r_mid)).tolist()})

    def job(duration_s, name):
        tracemalloc.reset_peak()
        start = tracemalloc.get_traced_memory()[0]
        s = loop.run_closed_loop(cfg(duration_s), f"{out}/{name}", progress=False)
        return {"frames": s["frames"], "skipped": s["run0"]["frames_skipped_eclipse"],
                "traced_peak": tracemalloc.get_traced_memory()[1] - start,
                "maxrss": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024}

    tracemalloc.start()
    job(2.0, "warm")  # the first job loads the detector, MuJoCo and Rerun: its peak is not the steady state's
    short = job(5.0, "short")
    long = job(long_s, "long")
    print(json.dumps({"short": short, "long": long}))
""")


def test_a_long_closed_loop_keeps_its_memory_flat(tmp_path):
    from envisat_pose.contracts import Estimates
    from envisat_pose.pipelines.common.job_defaults import default_weights_path
    from envisat_pose.pipelines.runs.rows import record_arrays

    out = subprocess.run([sys.executable, "-c", CHILD, default_weights_path(), str(tmp_path), "2099.9"],
                         capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stderr[-3000:]
    res = json.loads(out.stdout.strip().splitlines()[-1])
    short, long = res["short"], res["long"]
    T = long["frames"]
    assert T == 21000 and long["skipped"] == T, long  # every frame in the shadow: the test is about memory
    every_frame = T * sum(a.nbytes for a in record_arrays(1).values())
    grown = long["traced_peak"] - short["traced_peak"]
    print(f"\n{T} frames: traced peak {long['traced_peak'] / 2**20:.1f} MiB (short run {short['traced_peak'] / 2**20:.1f}), "
          f"peak RSS +{(long['maxrss'] - short['maxrss']) / 2**20:.1f} MiB; every frame held: {every_frame / 2**20:.1f} MiB")
    assert grown < every_frame, (grown / 2**20, every_frame / 2**20)
    # and the outputs are whole: every frame of the long run in est.npz and det.npz
    est = Estimates.load(str(tmp_path / "long" / "est.npz"))
    assert est.x_hat.shape == (1, T, 12) and est.P.shape == (1, T, 12, 12)
    with np.load(tmp_path / "long" / "det.npz", allow_pickle=False) as z:
        assert z["skipped"].all() and z["key"][-1] == f"frame-{T - 1:06d}"
    assert not (tmp_path / "long" / "runs").exists()  # the runs' chunk files are removed once streamed


def test_the_run_recording_is_cut_in_chunks_of_many_frames_and_has_its_footer(tmp_path):
    import rerun as rr
    import rerun_bindings

    from envisat_pose.analysis.recording import TrackRecorder, read_recording
    from envisat_pose.analysis.recording_stream import FILE_CHUNK_ROWS
    from envisat_pose.pipelines.runs.closed_loop import run_camera

    N = 2 * FILE_CHUNK_ROWS + 50
    rng = np.random.default_rng(0)
    path = tmp_path / "recording.rrd"
    rec = TrackRecorder(f"save:{path}", run_camera(64), with_truth=True)
    x = np.zeros(12)
    x[:3] = (0.5, 50.0, 0.3)
    for k in range(N):
        corners = rng.uniform(20.0, 40.0, (8, 2))
        est = {"t_s": float(k), "x_hat": x, "P": np.eye(12) * 0.01, "status": 1, "p_best": 0.9, "nis": 3.0,
               "nis_dof": 10, "corners_px": corners, "visible": np.ones(8, bool), "rejected": np.zeros(8, bool),
               "roi_px": np.array([10.0, 10.0, 40.0])}
        rec.log_frame(k, est, rng.integers(0, 255, (64, 64), dtype=np.uint8), x_true=x + 0.01,
                      corners_true_px=corners, in_frame=np.ones(8, bool))
        time.sleep(0.01)  # Rerun's default batcher would cut a chunk of every entity every 200 ms: ~20 frames
    rec.close()
    assert rerun_bindings.check_for_rrd_footer(str(path))  # its manifest: one entry per chunk of many frames
    rows = defaultdict(list)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a file without a footer warns
        reader = rr.chunk.RrdReader(str(path))
    for chunk in reader.stream():
        if not chunk.is_static:
            rows[chunk.entity_path].append(chunk.num_rows)
    per_frame = ["/world/chaser/camera/image", "/world/target", "/world/target_est", "/metrics/tracker/status",
                 "/metrics/error/position_m/x", "/world/chaser/camera/image/keypoints_detected"]
    for entity in per_frame:
        assert sum(rows[entity]) == N, (entity, rows[entity])
        assert len(rows[entity]) <= -(-N // FILE_CHUNK_ROWS), (entity, rows[entity])
    _, temporal = read_recording(str(path))  # and read back whole, without a warning
    assert temporal["/world/chaser/camera/image"]["frame"] == list(range(N))
