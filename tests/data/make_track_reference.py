"""Write tests/data/track_reference.npz: the estimates of two fixed, seeded tracks, recorded once on the code before
the refactors of issue 50 (items 2, 4, 5, 6: no behaviour change), read by tests/pipelines/test_track_reference.py.

The two tracks:
- closed: run_closed_loop on the default scenario, 256 px frames, 12 s at 1 Hz, seed 2, warm start (acquiring, then
  tracking: the Tracker's measure / bank / judge steps and the closed loop's run files);
- track: track_frames over a 21-frame sequence folder (`envisat generate --mode sequence`, 256 px, seed 7) with the
  default scenario's job (TrackConfig.from_scenario: the cold start's window and its first attempt; track.py's job and its scored run files).

For each, every array of est.npz and det.npz as a SHA-256 of its bytes (dtype and shape included: exact), and
x_hat, the diagonal of P and status in plain so that a failing comparison shows where the tracks part.

Run: .venv/bin/python tests/data/make_track_reference.py [--out tests/data/track_reference.npz]
"""

from __future__ import annotations

import argparse
import hashlib
import os
import sys
import tempfile

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
OUT = os.path.join(HERE, "track_reference.npz")


def digest(a: np.ndarray) -> str:
    """SHA-256 of an array's dtype, shape and bytes (C order)."""
    a = np.ascontiguousarray(a)
    h = hashlib.sha256(f"{a.dtype.str}{a.shape}".encode())
    h.update(a.tobytes())
    return h.hexdigest()


def summarize(out_dir: str, prefix: str) -> dict[str, np.ndarray]:
    """{prefix/...: array} of a track's output folder: digests of every array of est.npz and det.npz (strings
    apart: the config's JSON holds paths), x_hat, diag(P) and status in plain."""
    found = {}
    for name in ("est", "det"):
        with np.load(os.path.join(out_dir, f"{name}.npz"), allow_pickle=False) as z:
            for key in sorted(z.files):
                a = z[key]
                if a.dtype.kind in "US":
                    continue
                found[f"{prefix}/{name}/{key}"] = np.array(digest(a))
            if name == "est":
                found[f"{prefix}/x_hat"] = z["x_hat"]
                found[f"{prefix}/P_diag"] = np.diagonal(z["P"], axis1=-2, axis2=-1).copy()
                found[f"{prefix}/status"] = z["status"]
    return found


def closed_track(out_dir: str) -> dict[str, np.ndarray]:
    from envisat_pose.pipelines.closed_loop import run_closed_loop
    from envisat_pose.pipelines.run_config import RunConfig

    cfg = RunConfig.from_scenario("default", overrides={"duration_s": 12.0, "seed": 2, "warm_start": True,
                                                        "workers": 1, "image.resolution_px": 256})
    run_closed_loop(cfg, out_dir, progress=False)
    return summarize(out_dir, "closed")


def frames_track(work: str) -> dict[str, np.ndarray]:
    from envisat_pose.app.cli import main
    from envisat_pose.pipelines.track import TrackConfig, track_frames

    gen = os.path.join(work, "gen")
    assert main(["generate", "--mode", "sequence", "--scenario", "default", "--num-images", "21", "--seed", "7",
                 "--resolution", "256", "--workers", "1", "--out", gen, "--quiet"]) == 0
    out = os.path.join(work, "track")
    track_frames(TrackConfig.from_scenario("default"), gen, out_dir=out, progress=False)
    return summarize(out, "track")


def reference(work: str) -> dict[str, np.ndarray]:
    """Both tracks' arrays, computed in the folder work."""
    return {**closed_track(os.path.join(work, "closed")), **frames_track(work)}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default=OUT)
    args = p.parse_args(argv)
    with tempfile.TemporaryDirectory() as work:
        arrays = reference(work)
    np.savez_compressed(args.out, **arrays)
    print(f"wrote {args.out}: {len(arrays)} arrays, {os.path.getsize(args.out)} bytes", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
