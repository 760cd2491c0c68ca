"""The per-frame row store of a closed-loop run (and of `envisat track`): the arrays a run keeps per frame
(record_arrays), a tracker estimate written into its row (store_estimate), and RunRows, which streams the rows
to run_dir/<name>.npy CHUNK_FRAMES at a time with the run's reductions, so a run never holds all its frames."""

from __future__ import annotations

import os

import numpy as np

from envisat_pose.io import NpyRowWriter
from envisat_pose.status import ACQUIRING, LOST, STATUSES

# per-frame stages timed: the MuJoCo truth (its share per frame), MuJoCo rendering, the space camera, the detector,
# the filter (with the cold start's fits), the recording (encoding and logging run 0's frame)
STAGES = ("simulation", "rendering", "camera", "detection", "filtering", "recording")


def record_arrays(T: int, K: int = 8) -> dict:
    """The per-frame arrays a run keeps (one row per frame) of a target of K keypoints (ENVISAT's corners: 8)."""
    out = {k: np.zeros((T,), dtype=np.int64) for k in ("n_meas", "nis_dof", "naming", "status", "n_hypotheses")}
    out.update({"x_hat": np.empty((T, 12)), "P": np.empty((T, 12, 12)), "nis": np.zeros(T),
                "p_best": np.zeros(T), "corners_px": np.full((T, K, 2), np.nan),
                "cov_px": np.full((T, K, 2, 2), np.nan), "confidence": np.zeros((T, K)),
                "visible": np.zeros((T, K), bool), "rejected": np.zeros((T, K), bool),
                "alt_corners_px": np.full((T, K, 2), np.nan), "alt_probability": np.zeros(T),
                "ambiguous": np.zeros(T, bool), "crop_px": np.zeros((T, 3)), "roi_px": np.full((T, 3), np.nan),
                "converged": np.zeros(T, bool), "skipped": np.zeros(T, bool), "timing_s": np.zeros((T, len(STAGES)))})
    return out


def store_estimate(out: dict, k: int, est) -> None:
    """Row k of record_arrays from a TrackEstimate. While acquiring before any pose the state is NaN: it is kept
    as zeros with a NaN-free wide covariance so the Estimates contract (finite) holds; status says which."""
    from envisat_pose.pipelines.tracking.tracker_config import ACQUIRING_SIGMA

    if np.isfinite(est.x_hat).all():
        out["x_hat"][k], out["P"][k] = est.x_hat, est.P
    else:
        out["x_hat"][k], out["P"][k] = 0.0, np.diag(np.repeat(np.square(ACQUIRING_SIGMA), 3)) * 1e4
    out["status"][k] = STATUSES.index(est.status)
    out["n_hypotheses"][k] = len(est.probabilities)
    out["p_best"][k] = float(np.max(est.probabilities)) if len(est.probabilities) else 0.0
    out["nis"][k], out["nis_dof"][k] = est.nis, est.nis_dof
    out["n_meas"][k] = int((est.measured & ~est.rejected).sum())
    out["naming"][k] = est.naming
    out["rejected"][k] = est.rejected
    out["converged"][k] = est.converged
    if est.roi_px is not None:
        out["roi_px"][k] = est.roi_px
    fd = est.detection
    if fd is not None:
        vis = np.asarray(fd.visible, bool) & np.isfinite(fd.corners_px).all(-1) & np.isfinite(fd.cov_px).all((-1, -2))
        out["visible"][k] = vis
        out["corners_px"][k] = np.where(vis[:, None], fd.corners_px, np.nan)
        out["cov_px"][k] = np.where(vis[:, None, None], fd.cov_px, np.nan)
        out["confidence"][k] = np.where(vis, np.clip(np.nan_to_num(fd.confidence), 0.0, 1.0), 0.0)
        out["alt_corners_px"][k] = fd.alt_corners_px
        out["alt_probability"][k] = float(fd.alt_probability)
        out["ambiguous"][k] = bool(fd.ambiguous)
        out["crop_px"][k] = fd.crop_px


# rows a run holds before writing them out: ~2 kB a frame, so ~2 MB per run whatever the run's length
CHUNK_FRAMES = 1000
# columns of a run's arrays that go to det.npz (run 0) and est.npz (every run)
DET_KEYS = ("corners_px", "cov_px", "confidence", "visible", "rejected", "alt_corners_px", "alt_probability",
            "ambiguous", "crop_px", "roi_px", "converged", "skipped", "naming", "status", "p_best", "n_hypotheses")
EST_KEYS = ("x_hat", "P", "n_meas", "nis", "nis_dof")


class RunRows:
    """A run's per-frame arrays (record_arrays) streamed to run_dir/<name>.npy, `chunk` frames at a time, with
    the run's reductions (stage time sums, frame counts) taken per chunk: the run holds one chunk, never the run.
    Frames come in order: row(k) is frame k's row in `buf` (the chunk before it written out when full). K: the
    target's keypoints (ENVISAT's corners: 8)."""

    def __init__(self, run_dir: str, T: int, chunk: int = CHUNK_FRAMES, K: int = 8):
        os.makedirs(run_dir, exist_ok=True)
        self.T, self.chunk, self.start, self.n, self.K = T, min(chunk, T), 0, 0, K
        self.buf = record_arrays(self.chunk, K)
        self.writers = {k: NpyRowWriter(os.path.join(run_dir, f"{k}.npy"), T, a.shape[1:], a.dtype)
                        for k, a in self.buf.items()}
        self.sums = {"timing_s": np.zeros(len(STAGES)), "frames_skipped_eclipse": 0, "frames_roi": 0,
                     "frames_ambiguous": 0, "frames_acquiring": 0, "frames_lost": 0,
                     "timing_s_by_status": np.zeros((len(STATUSES), len(STAGES))),
                     "frames_by_status": np.zeros(len(STATUSES), np.int64)}

    def row(self, k: int) -> int:
        if k != self.start + self.n:
            raise ValueError(f"frame {k} out of order (expected {self.start + self.n})")
        if self.n == self.chunk:
            self.flush()
        self.n += 1
        return self.n - 1

    def flush(self) -> None:
        b = {k: a[:self.n] for k, a in self.buf.items()}
        for k, w in self.writers.items():
            w.write(b[k])
        s = self.sums
        s["timing_s"] += b["timing_s"].sum(axis=0)
        s["frames_skipped_eclipse"] += int(b["skipped"].sum())
        s["frames_roi"] += int(np.isfinite(b["roi_px"][:, 0]).sum())
        s["frames_ambiguous"] += int(b["ambiguous"].sum())
        s["frames_acquiring"] += int((b["status"] == ACQUIRING).sum())
        s["frames_lost"] += int((b["status"] == LOST).sum())
        np.add.at(s["timing_s_by_status"], b["status"], b["timing_s"])  # each frame's stages under its status
        s["frames_by_status"] += np.bincount(b["status"], minlength=len(STATUSES))
        self.start, self.n = self.start + self.n, 0
        self.buf = record_arrays(self.chunk, self.K)  # fresh defaults (NaN where a frame has no detection)

    def close(self) -> dict:
        """Write the last rows and check every frame was written; returns the run's reductions (plain data)."""
        if self.n:
            self.flush()
        for w in self.writers.values():
            w.close()
        return {**self.sums, "timing_s": self.sums["timing_s"].tolist(), "frames": self.T,
                "timing_s_by_status": self.sums["timing_s_by_status"].tolist(),
                "frames_by_status": self.sums["frames_by_status"].tolist()}


def timing_by_status(results: list[dict]) -> dict:
    """{status: {stage: ms per frame}} over the runs' reductions (RunRows.close), for the statuses some frame had:
    what an acquiring frame costs beside a tracked one."""
    t = np.sum([r["timing_s_by_status"] for r in results], axis=0)
    n = np.sum([r["frames_by_status"] for r in results], axis=0)
    return {name: {stage: float(1000 * t[i, j] / n[i]) for j, stage in enumerate(STAGES)}
            for i, name in enumerate(STATUSES) if n[i]}


def est_row(out: dict, k: int, t_s: float) -> dict:
    """Row k of a run's arrays (record_arrays or a RunRows chunk; at t_s, s) as the plain dict the recorder logs."""
    return {"t_s": t_s} | {name: out[name][k] for name in ("x_hat", "P", "status", "p_best", "n_hypotheses", "nis", "nis_dof",
                                             "corners_px", "visible", "rejected", "roi_px")}
