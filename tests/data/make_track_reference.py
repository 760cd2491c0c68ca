"""Write tests/data/track_reference.npz: every array of the est.npz and det.npz of two fixed, seeded tracks, read by
tests/pipelines/runs/test_track_reference.py (a guard against behaviour changes in refactors).

The two tracks:
- closed: run_closed_loop on the default scenario, 256 px frames, 12 s at 1 Hz, seed 2, warm start (acquiring, then
  tracking: the Tracker's measure / bank / judge steps and the closed loop's run files);
- track: track_frames over a 21-frame sequence folder (`envisat generate --mode sequence`, 256 px, seed 7) with the
  default scenario's job (TrackConfig(scenario="default"): the cold start's window and its first attempt; track.py's job
  and its scored run files).

The arrays pass through MuJoCo's renderer, BLAS and torch, so another machine gives them to within a few parts per
million (tolerances: tests/data/compare.py), not bit for bit. History: first recorded (as SHA-256 digests) on the
code before the refactors of issue 50 and reproduced bit for bit by the code after them on the machine that recorded
it; re-recorded whole on 2026-12-02 (an AMD EPYC with AVX-512) by the same code, whose estimates there differed from
the first recording by at most 7.6e-6 of each state's largest value. Re-recorded the same day for a change meant to
move the estimates: the sun's shadow map sized to the target (datagen/render.py, SHADOW_MAP_PX) moves shadow edges
in the closed loop's frames (its corners' alternative naming up to 7 % of a column's scale; statuses unchanged).
Re-recorded on 2026-12-03 for another: the measurement update in partial updates where the prior is far wider than
the measurement (filtering/step_update.py) takes the warm closed loop's first update from P0 in 16 steps (its
estimates up to 0.9 mm and its NIS up to 0.21 apart in the first frames, its detections' alternative naming up to
2.8e-3 of a column's scale through the window the estimate places; statuses equal; the cold track within its tolerance).
Re-recorded on 2026-12-06 for another: past split_max the partial updates' shares of the information grow
geometrically (step_update.split_factors), which the warm closed loop's first update from P0 takes (its covariance
up to 9.5e-3, NIS 2.9e-3 and estimates 3.4e-3 of a column's scale apart, its detections' alternative naming
1.9e-4; statuses equal; the cold track within its tolerance).

Run: .venv/bin/python tests/data/make_track_reference.py [--out tests/data/track_reference.npz]
"""

from __future__ import annotations

import os
import sys
import tempfile

import numpy as np

from envisat_pose.whole_flags import WholeFlagParser

HERE = os.path.dirname(os.path.abspath(__file__))
OUT = os.path.join(HERE, "track_reference.npz")


def summarize(out_dir: str, prefix: str) -> dict[str, np.ndarray]:
    """{prefix/est|det/key: array} of a track's output folder: every array of est.npz and det.npz but the strings
    (the config's JSON holds paths)."""
    found = {}
    for name in ("est", "det"):
        with np.load(os.path.join(out_dir, f"{name}.npz"), allow_pickle=False) as z:
            for key in sorted(z.files):
                if z[key].dtype.kind not in "US":
                    found[f"{prefix}/{name}/{key}"] = z[key]
    return found


def closed_track(out_dir: str) -> dict[str, np.ndarray]:
    from envisat_pose.pipelines.jobs import resolve_job
    from envisat_pose.pipelines.runs.closed_loop import run_closed_loop

    cfg = resolve_job("run", "default", overrides={"duration_s": 12.0, "seed": 2, "warm_start": True,
                                                   "workers": 1, "image.resolution_px": 256,
                                                   "render_window": False})  # the full-frame loop
    run_closed_loop(cfg, out_dir, progress=False)
    return summarize(out_dir, "closed")


def frames_track(work: str) -> dict[str, np.ndarray]:
    from envisat_pose.app.cli import main
    from envisat_pose.pipelines.runs.track import TrackConfig, track_frames

    gen = os.path.join(work, "gen")
    assert main(["generate", "--mode", "sequence", "--scenario", "default", "--num-images", "21", "--seed", "7",
                 "--resolution", "256", "--workers", "1", "--out", gen, "--quiet"]) == 0
    out = os.path.join(work, "track")
    track_frames(TrackConfig(scenario="default"), gen, out_dir=out, progress=False)
    return summarize(out, "track")


def reference(work: str) -> dict[str, np.ndarray]:
    """Both tracks' arrays, computed in the folder work."""
    return {**closed_track(os.path.join(work, "closed")), **frames_track(work)}


def main(argv=None) -> int:
    p = WholeFlagParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default=OUT)
    args = p.parse_args(argv)
    with tempfile.TemporaryDirectory() as work:
        arrays = reference(work)
    np.savez_compressed(args.out, **arrays)
    print(f"wrote {args.out}: {len(arrays)} arrays, {os.path.getsize(args.out)} bytes", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
