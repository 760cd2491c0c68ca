"""`envisat adapt` scored: before and after on foreign frames, the project's own renders of the same
poses as the reference, and what the adapted weights cost on the project's own renders.

Per (scenario, seed, resolution):
- foreign frames (bench/foreign_frames.py: MuJoCo Filament, a real camera's habits) as a user's folder; `adapt`
  over them (pipelines/adaptation/adapt.py, the shipped weights, its defaults) gives the before and after tracks;
- the same poses rendered by the project (`envisat generate --mode sequence`, same scenario, seed, frames, size),
  tracked with the shipped weights: the reference;
- each track scored against the truth (truth.npz / the generate labels; the truth only scores): the frame from
  which the pose stays right (pipelines/runs/scoring.settled_from: < 10 cm and < 1 deg, claimed, to the end), the
  second-half RMS position and attitude (frames with an estimate), the false-lock frames (claiming an estimate
  with attitude > 5 deg or position > 2 % of range), the held-out quarter's verdict (adopted or why not);
- PCK@5 of the adapted weights and of the shipped ones on the own renders (`envisat evaluate`);
- the pseudo-labels' range against the truth's (label_range): as smoothed, corrected by the sequence's edge scale,
  corrected frame by frame (pipelines/adaptation/edge_range.py; the report records the edge fits whatever --edge-range
  applies), so both ways of correcting are scored from one run.

Run:  .venv/bin/python bench/adapt.py --scenarios default --seeds 0 1 --resolutions 512 --num-images 300 \\
          --work /tmp/adapt-bench --out bench/results/adapt.json   [--params norm_heads] [--edge-range off]
(frames already under --work are reused; each --edge-range and --params adapts into its own folder
adapt-MODE-PARAMS.)

With `--responses RESPONSE:SIGMA[:bloom][:given] ...` the grid of camera responses (response curve, PSF, blooming)
instead: the project's own clean render of the sequence (bench/edge_truth.own_clean) put through the space camera
with that fixed camera response (edge_truth.response_params: response, Gaussian PSF sigma px, blooming), written as
a user's PNG folder with a camera.toml (its response and PSF in the file only with ':given'; else adapt estimates
them), adapted and scored as above (the frames' truth from the labels). The reference ('own') is the response
'linear:1.0' tracked with the shipped weights (the camera the detector was trained on, stored linearly). The rows
keep their keys and folders as first written ("look": the response given, "look_read": the report's record of
it; under --work, look-RESPONSE-SIGMA...). Example:
      .venv/bin/python bench/adapt.py --responses srgb:1.0 srgb:1.0:given linear:1.0 --seeds 9393 --num-images 240 \
          --work /tmp/adapt-bench --out bench/results/adapt_looks.json
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def scores(t_s: np.ndarray, x_true: np.ndarray, est_path: str, lit: np.ndarray) -> dict:
    """A track's figures against the truth x_true (T, 12): stays_right_from_frame, rms_position_m and
    rms_attitude_deg over the second half's frames with an estimate, false_lock_frames, tracked_frames."""
    from envisat_pose.pipelines.runs.scoring import claims_estimate, correct_frames, frame_errors

    with np.load(est_path) as est:
        x_hat, P, status = est["x_hat"][0], est["P"][0], est["status"][0]
    x_true = np.asarray(x_true).reshape(-1, 12)
    err = frame_errors(x_true, np.nan_to_num(x_hat), np.nan_to_num(P) + np.eye(12) * (~np.isfinite(P[:, 0, 0]))[
        :, None, None])
    claimed = claims_estimate(status)
    ok = claimed & (err["position_m"] < 0.10) & (err["attitude_deg"] < 1.0)
    ok_lit = ok | ~lit
    stays = None if not ok_lit[-1] else int(np.flatnonzero(~ok_lit)[-1] + 1 if (~ok_lit).any() else 0)
    half = np.arange(len(t_s)) >= len(t_s) // 2
    use = half & claimed
    rms = (lambda v: float(np.sqrt(np.mean(v[use] ** 2))) if use.any() else None)
    return {"stays_right_from_frame": stays, "rms_position_m": rms(err["position_m"]),
            "rms_attitude_deg": rms(err["attitude_deg"]),
            "false_lock_frames": int((claimed & ~correct_frames(err)).sum()),
            "tracked_frames": int((status == 1).sum())}


def label_range(report: dict, x_true: np.ndarray, pos_C_m: np.ndarray) -> dict | None:
    """The labelled frames' range error (m, label minus truth) as smoothed ('smoothed'), corrected by the
    sequence's edge scale ('sequence'), by each frame's ('frame'; unmeasured frames as smoothed): mean, RMS, and
    the frames measured. None without the edge record."""
    last = report["rounds"][-1]
    rec = last.get("edge_range")
    if not rec or "range_m" not in rec:
        return None
    k = np.asarray(last["label_frames"], int)
    r = np.asarray(rec["range_m"])
    r_true = np.linalg.norm(np.asarray(x_true).reshape(-1, 12)[k, :3] - pos_C_m, axis=1)
    d_seq = rec["sequence"]["delta"]
    d_frame = np.array([np.nan if d is None else d for d in rec["delta"]])
    ranges = {"smoothed": r, "sequence": r / (1.0 + (d_seq if d_seq is not None else 0.0)),
              "frame": np.where(np.isfinite(d_frame), r / (1.0 + np.nan_to_num(d_frame)), r)}
    out = {name: {"mean_m": float(np.mean(v - r_true)), "rms_m": float(np.sqrt(np.mean((v - r_true) ** 2)))}
           for name, v in ranges.items()}
    out.update(frames=int(len(k)), frames_measured=rec["frames_measured"], sequence_fit=rec["sequence"],
               applied=rec["mode"], range_true_median_m=float(np.median(r_true)))
    return out


def envisat(*args: str) -> None:
    subprocess.run([os.path.join(os.path.dirname(sys.executable), "envisat"), *args, "--quiet"], check=True,
                   stdout=subprocess.DEVNULL)


def pck5(weights: str, data: str, out_json: str) -> float:
    envisat("evaluate", "--weights", weights, "--data", data, "--json", out_json)
    with open(out_json) as fh:
        return float(json.load(fh)["groups"]["all"]["detector"]["pck_5px"])


def one_case(scenario: str, seed: int, res: int, n: int, work: str, steps: int | None, edge_range: str,
             params: str = "none") -> dict:
    sys.path.insert(0, os.path.join(ROOT, "bench"))
    import foreign_frames

    from envisat_pose.perception.weights import shipped_weights_path
    from envisat_pose.pipelines.adaptation.adapt import AdaptConfig, adapt
    from envisat_pose.pipelines.runs.frames import open_source
    from envisat_pose.pipelines.runs.track import TrackConfig
    from envisat_pose.resumable import manifest_path

    case = os.path.join(work, f"{scenario}-{seed}-{res}-{n}")
    foreign, own = os.path.join(case, "foreign"), os.path.join(case, "own")
    t0 = time.perf_counter()
    if not os.path.exists(os.path.join(foreign, "truth.npz")):
        foreign_frames.make_sequence(foreign, scenario, seed, n, res, progress=False)
    if not os.path.exists(manifest_path(own)):
        envisat("generate", "--mode", "sequence", "--scenario", scenario, "--seed", str(seed), "--num-images",
                str(n), "--resolution", str(res), "--workers", "1", "--out", own)
    t_make = time.perf_counter() - t0
    # the reference: the project's own renders of the same poses, the shipped weights
    envisat("track", "--images", own, "--out", os.path.join(case, "own-track"))
    with np.load(os.path.join(case, "own-track", "est.npz")) as est:
        t_own, x_own = est["t_s"], est["x_true"].reshape(-1, 12)[-len(est["t_s"]):]
    ref = scores(t_own, x_own, os.path.join(case, "own-track", "est.npz"), np.ones(len(t_own), bool))
    # adapt on the foreign frames (the truth is not handed to it)
    src = open_source(os.path.join(foreign, "frames"), timestamps=os.path.join(foreign, "timestamps.csv"))
    fields = {"edge_range": edge_range, "params": params} | ({} if steps is None else {"steps": steps})
    cfg = AdaptConfig(track=TrackConfig(scenario=scenario), **fields)
    t1 = time.perf_counter()
    run = os.path.join(case, f"adapt-{edge_range}-{params}")
    try:
        report = adapt(cfg, src, run, camera=os.path.join(foreign, "camera.toml"), progress=False)
        refused = None
    except Exception as err:  # too few trusted frames: recorded, the case scored before only
        report, refused = None, f"{type(err).__name__}: {err}"
    t_adapt = time.perf_counter() - t1
    with np.load(os.path.join(foreign, "truth.npz")) as tr:
        t_f, x_f, lit = tr["t_s"], tr["x"], ~tr["eclipse"].astype(bool)
    out = {"scenario": scenario, "seed": seed, "resolution_px": res, "frames": n, "edge_range": edge_range,
           "params": params, "own": ref,
           "make_s": t_make, "adapt_s": t_adapt, "refused": refused}
    if report is not None:
        out["before"] = scores(t_f, x_f, os.path.join(run, "before", "est.npz"), lit)
        out["after"] = scores(t_f, x_f, os.path.join(run, "after", "est.npz"), lit)
        out["adopted"], out["reason"] = report["adopted"], report["reason"]
        out["held_out"] = {"before": report["before"], "after": report["after"]}
        out["labels"] = report["rounds"][-1]["labels"]
        out["label_sigma_px_median"] = report["rounds"][-1]["label_sigma_px_median"]
        cal = report["rounds"][-1].get("calibration") or {}
        out["apparent_scale"] = {**(report["rounds"][-1].get("apparent_scale") or {}),
                                 "corners": cal.get("apparent_scale"), "corners_se": cal.get("apparent_scale_se"),
                                 "corners_frames": cal.get("apparent_scale_frames"),
                                 "adopted": report["rounds"][-1].get("apparent_scale_adopted")}
        from envisat_pose.pipelines.tracking.camera_file import camera_from_intrinsics

        cam_user, _ = camera_from_intrinsics(os.path.join(foreign, "camera.toml"))
        out["label_range"] = label_range(report, x_f, cam_user.pos_C_m)
        out["timing_s"] = report["timing_s"]
        if report["adopted"] and params == "none":  # the same network: its corners, so its PCK, unchanged
            out["pck5_own"] = {"same_network": True}
        elif report["adopted"]:
            out["pck5_own"] = {"shipped": pck5(shipped_weights_path(), own, os.path.join(case, "eval-shipped.json")),
                               "adapted": pck5(os.path.join(run, "detector.safetensors"), own,
                                               os.path.join(case, "eval-adapted.json"))}
    return out


def response_folder(clean: str, spec: str, seed: int, res: int, out: str) -> str:
    """The clean sequence `clean` through the space camera's fixed camera response
    spec='RESPONSE:SIGMA[:bloom][:given]' as a user's folder out/: frames/*.png, timestamps.csv, camera.toml,
    truth.npz (x, t_s; scoring only). Made when missing; returns out."""
    import cv2

    sys.path.insert(0, os.path.join(ROOT, "bench"))
    import edge_truth

    from envisat_pose.datagen.sensor import apply_sensor

    if os.path.exists(os.path.join(out, "truth.npz")):
        return out
    parts = spec.split(":")
    response, sigma, bloom, given = parts[0].replace("gamma", "gamma "), float(parts[1]), "bloom" in parts, \
        "given" in parts
    frames = edge_truth.clean_frames(clean, 1)
    os.makedirs(os.path.join(out, "frames"), exist_ok=True)
    names, t_s, x = [], [], []
    for k, (im, lab) in enumerate(frames):
        p = {**edge_truth.response_params(response, sigma, bloom, res, seed), "noise_seed": 7000 + k}
        names.append(f"frame_{k:05d}.png")
        cv2.imwrite(os.path.join(out, "frames", names[-1]), apply_sensor(im, p))
        t_s.append(float(lab["scene"]["t_s"]) if "t_s" in lab.get("scene", {}) else float(k))
        x.append(lab["x"])
    with open(os.path.join(out, "timestamps.csv"), "w") as fh:
        fh.write("file,t_s\n" + "".join(f"{n},{t!r}\n" for n, t in zip(names, t_s)))
    K = np.asarray(frames[0][1]["K"], float)
    extra = (f'response = "{response}"\npsf_sigma_px = {sigma}\n' if given else "")
    with open(os.path.join(out, "camera.toml"), "w") as fh:
        fh.write(f"fx = {float(K[0, 0])!r}\nfy = {float(K[1, 1])!r}\ncx = {float(K[0, 2])!r}\n"
                 f"cy = {float(K[1, 2])!r}\nwidth = {res}\n"
                 f"height = {res}\n{extra}")
    np.savez(os.path.join(out, "truth.npz"), x=np.asarray(x, float), t_s=np.asarray(t_s, float))
    return out


def response_case(spec: str, scenario: str, seed: int, res: int, n: int, work: str) -> dict:
    """One camera response of the grid (module doc, spec 'RESPONSE:SIGMA[:bloom][:given]'): adapt on its
    folder, before and after scored against the labels' truth, beside the reference response's track."""
    sys.path.insert(0, os.path.join(ROOT, "bench"))
    import edge_truth

    from envisat_pose.pipelines.adaptation.adapt import AdaptConfig, adapt
    from envisat_pose.pipelines.runs.frames import open_source
    from envisat_pose.pipelines.runs.track import TrackConfig, prepare_frames, track_frames

    clean = edge_truth.own_clean(scenario, seed, res, n, work)
    case = os.path.join(work, f"{scenario}-{seed}-{res}-{n}")
    out = {"scenario": scenario, "seed": seed, "resolution_px": res, "frames": n, "look": spec}
    folder = response_folder(clean, spec, seed, res, os.path.join(case, "look-" + spec.replace(":", "-")))
    with np.load(os.path.join(folder, "truth.npz")) as tr:
        t_f, x_f = tr["t_s"], tr["x"]
    lit = np.ones(len(t_f), bool)
    src = open_source(os.path.join(folder, "frames"), timestamps=os.path.join(folder, "timestamps.csv"))
    run = os.path.join(folder, "adapt")
    t1 = time.perf_counter()
    try:
        report = adapt(AdaptConfig(track=TrackConfig(scenario=scenario)), src, run,
                       camera=os.path.join(folder, "camera.toml"), progress=False)
        out["refused"] = None
    except Exception as err:  # too few trusted frames: recorded
        report, out["refused"] = None, f"{type(err).__name__}: {err}"
    out["adapt_s"] = time.perf_counter() - t1
    if report is not None:
        last = report["rounds"][-1]
        out["before"] = scores(t_f, x_f, os.path.join(run, "before", "est.npz"), lit)
        out["after"] = scores(t_f, x_f, os.path.join(run, "after", "est.npz"), lit)
        for name in ("before", "after"):
            out[name]["range_error_2nd_half_m"] = range_error(t_f, x_f, os.path.join(run, name, "est.npz"))
        out.update(adopted=report["adopted"], reason=report["reason"], scale_note=report.get("scale_note"),
                   apparent_scale=last.get("apparent_scale"), **{"look_read": last["edge_range"].get("look")},
                   edge_sequence=last["edge_range"]["sequence"])
    ref = response_folder(clean, "linear:1.0", seed, res, os.path.join(case, "look-linear-1.0"))  # after: slower
    ref_track = os.path.join(ref, "track")
    if not os.path.exists(os.path.join(ref_track, "est.npz")):
        src = open_source(os.path.join(ref, "frames"), timestamps=os.path.join(ref, "timestamps.csv"))
        tcfg, src, cam, remap, _ = prepare_frames(TrackConfig(scenario=scenario), src,
                                                  os.path.join(ref, "camera.toml"))
        track_frames(tcfg, src, cam, remap, ref_track, progress=False)
    out["own"] = scores(t_f, x_f, os.path.join(ref_track, "est.npz"), lit)
    out["own"]["range_error_2nd_half_m"] = range_error(t_f, x_f, os.path.join(ref_track, "est.npz"))
    return out


def range_error(t_s: np.ndarray, x_true: np.ndarray, est_path: str) -> float | None:
    """The second half's mean range error (m, estimate minus truth, frames with a claimed estimate), range from
    the chaser's camera: the target's position norm (the camera sits at the chaser's origin to a few cm, common to
    both)."""
    from envisat_pose.pipelines.runs.scoring import claims_estimate

    with np.load(est_path) as est:
        x_hat, status = est["x_hat"][0], est["status"][0]
    x_true = np.asarray(x_true).reshape(-1, 12)
    use = claims_estimate(status) & (np.arange(len(t_s)) >= len(t_s) // 2)
    if not use.any():
        return None
    return float(np.mean(np.linalg.norm(x_hat[use, :3], axis=1) - np.linalg.norm(x_true[use, :3], axis=1)))


def table(rows: list[dict]) -> str:
    def f(v, fmt):
        return "-" if v is None else format(v, fmt)

    lines = ["| scenario | seed | px | run | stays right from | 2nd-half RMS pos | att | false locks |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        for name in ("own", "before", "after"):
            s = r.get(name)
            if s is None:
                continue
            lines.append(f"| {r['scenario']} | {r['seed']} | {r['resolution_px']} | {name} | "
                         f"{f(s['stays_right_from_frame'], 'd')} | {f(s['rms_position_m'] and 100 * s['rms_position_m'], '.1f')} cm | "
                         f"{f(s['rms_attitude_deg'], '.2f')} deg | {s['false_lock_frames']} |")
        lines.append(f"| | | | adopted: {r.get('adopted')} | {r.get('reason') or r.get('refused') or ''} | "
                     f"adapt {r['adapt_s']:.0f} s | | |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    from _common import WholeFlagParser, count, description, out_file, provenance, write_json  # bench/_common.py

    ap = WholeFlagParser(description=description(__doc__))
    ap.add_argument("--scenarios", nargs="+", default=["default"])
    ap.add_argument("--seeds", nargs="+", type=count(0), default=[0, 1])
    ap.add_argument("--resolutions", nargs="+", type=count(), default=[512])
    ap.add_argument("--num-images", type=count(), default=300)
    ap.add_argument("--steps", type=count(), help="fine-tune steps (default: AdaptConfig's)")
    ap.add_argument("--work", default="/tmp/adapt-bench")
    ap.add_argument("--edge-range", default="sequence", choices=["sequence", "frame", "off"],
                    help="AdaptConfig.edge_range: how the labels' range is corrected by the silhouette edges")
    ap.add_argument("--params", default="none", choices=["none", "norm_heads", "all"],
                    help="AdaptConfig.params: what the fine-tune trains ('none': recalibration only)")
    ap.add_argument("--out", type=out_file, default=os.path.join(ROOT, "bench", "results", "adapt.json"))
    ap.add_argument("--responses", nargs="+",
                    help="the grid of camera responses on own renders (module doc): RESPONSE:SIGMA...")
    args = ap.parse_args(argv)
    prov = provenance(args)
    os.environ.setdefault("MUJOCO_GL", "osmesa")
    rows = []
    if args.responses:
        for seed in args.seeds:
            for spec in args.responses:
                rows.append(response_case(spec, args.scenarios[0], seed, args.resolutions[0], args.num_images,
                                          args.work))
                write_json(args.out, {"cases": rows, "cores": os.cpu_count(), "argv": sys.argv[1:], "provenance": prov},
                           indent=1)
                print(json.dumps({k: rows[-1].get(k) for k in ("look", "own", "before", "after", "adopted",
                                                               "reason", "scale_note", "refused")}), flush=True)
        return 0
    for scenario in args.scenarios:
        for res in args.resolutions:
            for seed in args.seeds:
                rows.append(one_case(scenario, seed, res, args.num_images, args.work, args.steps, args.edge_range,
                                     args.params))
                # after each case: a killed run keeps what it measured
                write_json(args.out, {"cases": rows, "cores": os.cpu_count(), "argv": sys.argv[1:], "provenance": prov},
                           indent=1)
                print(table(rows[-1:]), flush=True)
    print(table(rows))
    return 0


if __name__ == "__main__":
    from _common import run_main  # bench/_common.py, beside this script

    run_main(main)
