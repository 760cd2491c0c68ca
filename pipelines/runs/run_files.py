"""The runs' files of `envisat run` and `envisat track`, read back chunk by chunk: each run writes its per-frame
arrays to RUN/<name>.npy (pipelines/runs/rows.py's RunRows); the job scores and checks them (score_run_files), streams
est.npz and det.npz from them (write_run_files: the same bytes as saving the whole arrays) and draws errors.png from
at most PLOT_FRAMES frames (plot_inputs), so memory does not grow with the run's length.
"""

from __future__ import annotations

import os

import numpy as np

from envisat_pose.contracts import Detections, Estimates
from envisat_pose.io import StreamedArray, npy_info, read_npy_rows, save_npz
from envisat_pose.pipelines.runs.outputs import no_estimate_nan
from envisat_pose.pipelines.runs.rows import CHUNK_FRAMES, DET_KEYS, EST_KEYS
from envisat_pose.state import error_summary
from envisat_pose.status import LOST, legend_json

# the most frames errors.png draws per series: beyond it every k-th frame (a 13-inch figure at 100 dpi shows
# ~400 px per panel; drawing every frame of a long run would hold every run's covariances at once)
PLOT_FRAMES = 7200


def run_rows(run_dir: str, names, start: int, stop: int) -> dict:
    """Frames [start, stop) of a run's arrays `names` (RunRows' files), read from the files."""

    return {k: read_npy_rows(os.path.join(run_dir, f"{k}.npy"), start, stop) for k in names}


def run_array(run_dirs: list[str], name: str, T: int):
    """The runs' array `name` stacked over runs, (R, T, ...), as an io.StreamedArray read chunk by chunk."""

    shape, dtype, _ = npy_info(os.path.join(run_dirs[0], f"{name}.npy"))

    def chunks():
        for d in run_dirs:
            for a in range(0, T, CHUNK_FRAMES):
                yield read_npy_rows(os.path.join(d, f"{name}.npy"), a, a + CHUNK_FRAMES)

    return StreamedArray((len(run_dirs),) + tuple(shape), dtype, chunks)


def estimate_arrays(run_dirs: list[str], T: int) -> dict:
    """est.npz's per-run arrays (rows.EST_KEYS and status, each (R, T, ...)) streamed from the runs' files,
    x_hat and P NaN on rows without an estimate."""

    est = {k: run_array(run_dirs, k, T) for k in EST_KEYS + ("status",)}
    for k in ("x_hat", "P"):
        def chunks(k=k):
            for d in run_dirs:
                for a in range(0, T, CHUNK_FRAMES):
                    c = run_rows(d, [k, "status"], a, a + CHUNK_FRAMES)
                    yield no_estimate_nan(c[k], c["status"])

        est[k] = StreamedArray(est[k].shape, np.float64, chunks)
    return est


def score_run_files(t_s: np.ndarray, x_true: np.ndarray, run_dirs: list[str], paths: dict, config_json: str,
                    det_cfg: str, score: bool = True, det_names=DET_KEYS, equivalent=None,
                    dark: np.ndarray | None = None, chart: str = "additive") -> dict | None:
    """scoring.score_runs of the runs in run_dirs against x_true (T, 12), reading x_hat and P chunk by chunk;
    each chunk is also checked as est.npz's and (run 0) det.npz's contracts check them on save (score False: only
    the checks, for x_true all NaN, no truth; returns None). Keeps only per-frame scalars (the errors, status)
    and the second half's estimates for the error summary. equivalent: (E, 3, 3) the target's rotations nothing
    tells apart (scoring.nearest_truth; None: none). dark: (T,) frames the truth says are unlit (a dataset's
    eclipse), scored as frames without an image (skipped) are: times 'to' something count from the first lit one.
    chart: the runs' filter's sigma_chart, P's (scoring.frame_errors)."""
    from envisat_pose.pipelines.runs.scoring import frame_errors, nearest_truth, score_frames, summary_after_s

    T = len(t_s)
    errors, status = [], []
    for r, d in enumerate(run_dirs):
        parts, st = [], []
        for a in range(0, T, CHUNK_FRAMES):
            b = min(a + CHUNK_FRAMES, T)
            c = run_rows(d, set(EST_KEYS + ("status",) + (det_names if r == 0 else ())), a, b)
            Estimates.validated({"t_s": t_s[a:b], "x_true": x_true[None, a:b], "diverged": np.zeros(1, bool),
                                 "config_json": config_json} | {k: c[k][None] for k in EST_KEYS}, paths["est"])
            if r == 0:
                Detections.validated({"t_s": t_s[a:b], "config_json": det_cfg} | {k: c[k] for k in det_names},
                                     paths["det"])
            if not score:
                continue
            parts.append(frame_errors(nearest_truth(x_true[a:b], c["x_hat"], equivalent), c["x_hat"], c["P"], chart))
            st.append(c["status"])
        if score:
            errors.append({k: np.concatenate([p[k] for p in parts]) for k in parts[0]})
            status.append(np.concatenate(st))
    if not score:
        return None
    errors = {k: np.stack([e[k] for e in errors]) for k in errors[0]}
    after_s = summary_after_s(t_s)
    first = int(np.argmax(t_s >= after_s))
    late_rows = [run_rows(d, ["x_hat", "status"], first, T) for d in run_dirs]  # no estimate: NaN, as in est.npz
    x_late = np.stack([no_estimate_nan(c["x_hat"], c["status"]) for c in late_rows])
    x_true_late = x_true[first:] if equivalent is None or not len(equivalent) else \
        nearest_truth(x_true[first:], x_late, equivalent)
    summary = error_summary(t_s[first:], x_true_late, x_late, after_s)
    skipped = run_rows(run_dirs[0], ["skipped"], 0, T)["skipped"]
    if dark is not None:
        skipped = skipped | np.asarray(dark, bool)
    return score_frames(t_s, errors, np.stack(status), skipped, summary)


def lost_runs(run_dirs: list[str], T: int) -> np.ndarray:
    """(R,) bool: the runs in which the tracker declared a frame lost (Estimates.diverged for tracker runs)."""

    return np.array([bool(np.any(run_rows(d, ["status"], 0, T)["status"] == LOST)) for d in run_dirs])


def write_run_files(paths: dict, t_s: np.ndarray, x_true: np.ndarray, run_dirs: list[str], diverged: np.ndarray,
                    config_json: str, keys: list[str], det_cfg: str, det_names=DET_KEYS,
                    extra: dict | None = None) -> None:
    """est.npz (every run) and det.npz (run 0) streamed from the runs' files (their contracts checked chunk by
    chunk in score_run_files): the same bytes as Estimates.save / save_npz of the whole arrays. diverged (R,):
    Estimates.diverged; extra: more (R,) arrays for est.npz (Estimates.load ignores them)."""

    T, R = len(t_s), len(run_dirs)
    est = estimate_arrays(run_dirs, T)  # status per row, NaN where no estimate
    est["x_true"] = StreamedArray((R, T, 12), np.float64, lambda: (x_true for _ in range(R)))
    save_npz(paths["est"], est | (extra or {}) | {"t_s": t_s, "diverged": np.asarray(diverged, bool),
                                  "config_json": np.array(config_json), "status_legend": np.array(legend_json())})
    det = {k: run_array(run_dirs[:1], k, T) for k in det_names}
    det = {k: StreamedArray(a.shape[1:], a.dtype, a.chunks) for k, a in det.items()}
    key_dtype = np.dtype(f"<U{max(max(map(len, keys), default=1), 1)}")  # as numpy.array(keys) makes it
    det["key"] = StreamedArray((T,), key_dtype, lambda: (np.array(keys[a:a + CHUNK_FRAMES], key_dtype)
                                                         for a in range(0, T, CHUNK_FRAMES)))
    save_npz(paths["det"], det | {"t_s": t_s, "config_json": np.array(det_cfg), "status_legend": np.array(legend_json())})


def plot_inputs(t_s: np.ndarray, x_true: np.ndarray, run_dirs: list[str]) -> tuple:
    """What plots.plot_estimate draws (t_s, x_true, x_hat, P) at most PLOT_FRAMES frames (every k-th), read from
    the runs' files: P as its mean over the runs with an estimate at that frame (the figure's filter sigma is that
    mean's diagonal) on the diagonal, one run, so the figure holds one covariance series whatever the number of
    runs. A frame without an estimate (acquiring, lost: the filter's placeholder in the rows) is NaN, as in
    est.npz: a gap in the figure, not a line at the placeholder that sets the axes."""
    T = len(t_s)
    step = -(-T // PLOT_FRAMES)
    idx = np.arange(0, T, step)
    x_hat, p_sum, n = [], np.zeros((len(idx), 12)), np.zeros((len(idx), 1))
    for d in run_dirs:
        xs, ps = [], []
        for a in range(0, T, CHUNK_FRAMES):
            c = run_rows(d, ["x_hat", "P", "status"], a, a + CHUNK_FRAMES)
            take = slice((-a) % step, None, step)
            xs.append(no_estimate_nan(c["x_hat"][take], c["status"][take]))
            ps.append(no_estimate_nan(np.diagonal(c["P"][take], axis1=-2, axis2=-1), c["status"][take]))
        x_hat.append(np.concatenate(xs))
        p_run = np.concatenate(ps)
        known = np.isfinite(p_run).all(-1, keepdims=True)
        p_sum, n = p_sum + np.where(known, p_run, 0.0), n + known
    P = np.zeros((1, len(idx), 12, 12))
    P[0][:, np.arange(12), np.arange(12)] = np.where(n > 0, p_sum / np.maximum(n, 1), np.nan)
    return t_s[idx], np.repeat(x_true[idx][None], len(run_dirs), axis=0), np.stack(x_hat), P
