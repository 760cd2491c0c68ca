"""The edge cue (pipelines/adaptation/edge_range.py) read at the true pose of foreign frames: what it says where the answer is
known, so its own bias is separated from the tracker's.

Per (scenario, seed, resolution), on the foreign sequence bench/adapt.py renders (bench/foreign_frames.py:
MuJoCo Filament, a real camera's habits; made here when missing) and every `--stride`-th frame, remapped to the
pinhole as the tracker sees them:
- the sequence's delta (edge_range.sequence_scale over the frames' fits) with the outline projected at the true
  pose, and at the true pose with the range scaled by 1 -+ `--step` (the cue's gain: it should read -+ step);
- the stations' offsets (px, + outward) at the true pose by the brightness of the face inside the edge (grey
  levels 5 px in): where the renderer's shading moves the edge.
A perfect cue reads 0 at the true pose; its reading there is the part of adapt's range correction that no
tracker can remove. The truth is the bench's, never the library's.

With `--responses` the grid of camera responses (response curve, PSF, blooming) on the project's own renders
instead: one clean sequence per (seed, resolution) (`envisat generate --mode sequence`, storage 'clean'), every
`--stride`-th frame put through the space camera (datagen/sensor.py) with a fixed camera response: response linear,
sRGB, gamma 1.8 or 2.4; Gaussian PSF sigma 0.3 / 1.0 / 2.5 px; blooming off (white at 0.8 of the full well) or on
(1.5, 4 px spill); no motion blur, no vignetting. Per camera response the sequence's delta at the labels' true
corners: in the stored values (the cue as it was), linearized by the known response with the reach of the known
PSF, and by the response and PSF the frames give (pipelines/adaptation/edge_response.estimate_response); and the
estimate itself. The Filament rows (without --responses) record the same three readings, their response unknown.
The results keep their keys as first written ("looks": the rows, "estimated_look": the estimate).

Run:  .venv/bin/python bench/edge_truth.py --seeds 0 1 2 3 --resolutions 512 1024 --work /tmp/adapt-bench
(writes bench/results/edge_truth.json and prints a table);
      .venv/bin/python bench/edge_truth.py --responses --seeds 0 --resolutions 512 1024 --work /tmp/adapt-bench \
          --out bench/results/edge_truth_looks.json
"""

from __future__ import annotations

import json
import os
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
BRIGHTNESS = ((0, 40), (40, 60), (60, 90), (90, 130), (130, 256))


def one_case(scenario: str, seed: int, res: int, n: int, work: str, stride: int, step: float) -> dict:
    import cv2

    sys.path.insert(0, os.path.join(ROOT, "bench"))
    import foreign_frames

    from envisat_pose.pipelines.adaptation.edge_range import correct_range, edge_stations, fit_scale, sequence_scale
    from envisat_pose.pipelines.adaptation.pseudo_labels import corner_labels
    from envisat_pose.pipelines.runs.frames import open_source
    from envisat_pose.pipelines.runs.track import TrackConfig, prepare_frames

    foreign = os.path.join(work, f"{scenario}-{seed}-{res}-{n}", "foreign")
    if not os.path.exists(os.path.join(foreign, "truth.npz")):
        foreign_frames.make_sequence(foreign, scenario, seed, n, res, progress=False)
    src = open_source(os.path.join(foreign, "frames"), timestamps=os.path.join(foreign, "timestamps.csv"))
    _, source, camera, remap, _ = prepare_frames(TrackConfig(scenario=scenario), src,
                                                 os.path.join(foreign, "camera.toml"))
    with np.load(os.path.join(foreign, "truth.npz")) as tr:
        x = tr["x"].reshape(-1, 12)
    keep = set(range(0, len(x), stride))
    images = {k: (im if remap is None else cv2.remap(im, remap[0], remap[1], cv2.INTER_LINEAR))
              for k, im in source.frames() if k in keep}
    ks = sorted(images)
    out = {"scenario": scenario, "seed": seed, "resolution_px": res, "frames": len(ks)}
    offsets, inside = [], []
    for e in (-step, 0.0, step):
        xs = correct_range(x[ks], camera.pos_C_m, -e / (1.0 + e))  # range r -> r (1 + e)
        lab = corner_labels(xs, camera)
        fits = []
        for i, k in enumerate(ks):
            st = edge_stations(images[k], lab["corners_px"][i], lab["visible"][i] & lab["in_frame"][i])
            fits.append(fit_scale(st))
            if e == 0.0 and len(st.offset_px):
                p = np.round(st.point_px - 5.0 * st.normal).astype(int)
                offsets.append(st.offset_px)
                inside.append(images[k][p[:, 1], p[:, 0]].astype(float))
        seq = sequence_scale(fits)
        out[f"range_x{1 + e:.4f}"] = {"delta": seq.delta, "delta_se": seq.delta_se,
                                      "frames_measured": int(sum(f.delta is not None for f in fits))}
    lab = corner_labels(x[ks], camera)
    out["readings"] = three_readings([images[k] for k in ks], lab["corners_px"], lab["visible"] & lab["in_frame"])
    off, br = np.concatenate(offsets), np.concatenate(inside)
    out["offset_px_by_inside_grey"] = [
        {"grey": [lo, hi], "stations": int(m.sum()), "mean_px": float(off[m].mean()),
         "median_px": float(np.median(off[m]))}
        for lo, hi in BRIGHTNESS for m in [(br >= lo) & (br < hi)] if m.sum() >= 20]
    out["offset_px_mean"], out["stations"] = float(off.mean()), int(len(off))
    return out


RESPONSES = ("linear", "srgb", "gamma 1.8", "gamma 2.4")
PSF_SIGMAS_PX = (0.3, 1.0, 2.5)
RESPONSE_FRAMES = 20  # frames of a sequence the response and blur are estimated from (evenly spread)


def own_clean(scenario: str, seed: int, res: int, n: int, work: str) -> str:
    """A clean own-render sequence (storage 'clean'), made when missing: its folder."""
    import subprocess

    out = os.path.join(work, f"{scenario}-{seed}-{res}-{n}", "own-clean")
    from envisat_pose.resumable import manifest_path

    if not os.path.exists(manifest_path(out)):
        os.makedirs(os.path.dirname(out), exist_ok=True)
        toml = out + ".toml"
        with open(toml, "w") as fh:
            fh.write('storage = "clean"\n')
        subprocess.run([os.path.join(os.path.dirname(sys.executable), "envisat"), "generate", "--config", toml,
                        "--mode", "sequence", "--scenario", scenario, "--seed", str(seed), "--num-images", str(n),
                        "--resolution", str(res), "--workers", "1", "--out", out, "--quiet"], check=True)
    return out


def clean_frames(folder: str, stride: int) -> list[tuple[np.ndarray, dict]]:
    """Every stride-th (clean image (H, W) uint8, label) of a generated sequence, in order."""
    import glob

    from envisat_pose.datagen.dataset import decode_png
    from envisat_pose.shard_reader import read_shards

    out = []
    for i, (_, _, m) in enumerate(read_shards(sorted(glob.glob(os.path.join(folder, "*.tar"))))):
        if i % stride == 0:
            out.append((decode_png(m["png"]), json.loads(m["json"])))
    return out


def response_params(response: str, sigma_px: float, bloom: bool, res: int, seed: int) -> dict:
    """The space camera's parameters of one fixed camera response (datagen/sensor.draw_sensor over degenerate
    ranges)."""
    from envisat_pose.config import to_dict
    from envisat_pose.datagen.generate_config import SensorConfig
    from envisat_pose.datagen.sensor import draw_sensor

    fill = (1.5, 1.5) if bloom else (0.8, 0.8)
    cfg = SensorConfig(exposure_s=(0.005, 0.005), full_well_e=(20000.0, 20000.0), white_fill=fill,
                       read_noise_e=(5.0, 5.0), dark_current_e_per_s=(50.0, 50.0), adc_bits=(12,),
                       blooming_decay_px=(4.0, 4.0), psf="gaussian",
                       psf_sigma_px_1024=(sigma_px * 1024.0 / res,) * 2, vignetting_cos_power=(0.0, 0.0),
                       response=response)
    return draw_sensor(to_dict(cfg), res, 1.0, 0.0, 0.0, np.random.default_rng(seed))


def sequence_delta(images, corners, use, light=None, blur_px=None) -> dict:
    """The sequence's delta at the given corners (edge_range.sequence_scale over the frames' fits)."""
    from envisat_pose.pipelines.adaptation.edge_range import frame_scale, sequence_scale

    fits = [frame_scale(im, c, u, light=light, blur_px=blur_px) for im, c, u in zip(images, corners, use)]
    seq = sequence_scale(fits)
    return {"delta": seq.delta, "delta_se": seq.delta_se, "frames_measured": int(sum(f.delta is not None
                                                                                      for f in fits))}


def three_readings(images, corners, use, known=None, blur_px=None) -> dict:
    """The cue in the stored values, by the known response and blur (when given), by the estimated ones."""
    from envisat_pose.pipelines.adaptation.edge_response import estimate_response

    pick = np.unique(np.linspace(0, len(images) - 1, min(len(images), RESPONSE_FRAMES)).round().astype(int))
    fit = estimate_response([images[i] for i in pick], corners[pick], use[pick])
    out = {"stored": sequence_delta(images, corners, use), "estimated_look": fit.record(),
           "estimated": sequence_delta(images, corners, use, fit.response, fit.psf_sigma_px)}
    if known is not None:
        out["known"] = sequence_delta(images, corners, use, known, blur_px)
    return out


def responses_case(scenario: str, seed: int, res: int, n: int, work: str, stride: int) -> list[dict]:
    """The grid of camera responses on one own-render sequence (module doc): one row per response."""
    from envisat_pose.camera_response import parse_response
    from envisat_pose.datagen.sensor import apply_sensor

    frames = clean_frames(own_clean(scenario, seed, res, n, work), stride)
    corners = np.array([lab["corners_px"] for _, lab in frames], float)
    use = np.array([np.asarray(lab["visible"], bool) & np.asarray(lab["in_frame"], bool) for _, lab in frames])
    rows = []
    for response in RESPONSES:
        for sigma in PSF_SIGMAS_PX:
            for bloom in (False, True):
                t0 = time.perf_counter()
                images = [apply_sensor(im, {**response_params(response, sigma, bloom, res, seed),
                                            "noise_seed": 1000 + k}) for k, (im, _) in enumerate(frames)]
                row = {"scenario": scenario, "seed": seed, "resolution_px": res, "frames": len(frames),
                       "response": response, "psf_sigma_px": sigma, "blooming": bloom,
                       **three_readings(images, corners, use, parse_response(response, "response"), sigma)}
                row["seconds"] = time.perf_counter() - t0
                rows.append(row)
                print(responses_line(row), flush=True)
    return rows


def responses_line(r: dict) -> str:
    pct = (lambda v: "-" if v is None else f"{100 * v:+.3f} %")
    lk = r["estimated_look"]
    return (f"| {r['scenario']} | {r['seed']} | {r['resolution_px']} | {r['response']} | {r['psf_sigma_px']} | "
            f"{'on' if r['blooming'] else 'off'} | {pct(r['stored']['delta'])} | "
            f"{pct(r.get('known', {}).get('delta'))} | {pct(r['estimated']['delta'])} | {lk['response']} "
            f"({'-' if lk['gamma'] is None else format(lk['gamma'], '.2f')}), psf {lk['psf_sigma_px'] or 0:.2f} |")


def main(argv: list[str] | None = None) -> int:
    from _common import WholeFlagParser, count, description, out_file, positive, provenance  # bench/_common.py

    ap = WholeFlagParser(description=description(__doc__))
    ap.add_argument("--scenarios", nargs="+", default=["default"])
    ap.add_argument("--seeds", nargs="+", type=count(0), default=[0, 1, 2, 3])
    ap.add_argument("--resolutions", nargs="+", type=count(), default=[512])
    ap.add_argument("--num-images", type=count(), default=300)
    ap.add_argument("--stride", type=count(), default=3)
    ap.add_argument("--step", type=positive, default=0.005)
    ap.add_argument("--work", default="/tmp/adapt-bench")
    ap.add_argument("--out", type=out_file, default=os.path.join(ROOT, "bench", "results", "edge_truth.json"))
    ap.add_argument("--responses", action="store_true", help="the grid of camera responses on own renders (module doc)")
    args = ap.parse_args(argv)
    os.environ.setdefault("MUJOCO_GL", "osmesa")
    from envisat_pose.datagen.scenario import scenario_dict

    for name in args.scenarios:  # a wrong name is one line here, not a child's failure later
        scenario_dict(name)
    if args.responses:
        from envisat_pose.config import ConfigError

        for res in args.resolutions:  # a size the grid's widest blur does not fit: one line before any render
            try:
                response_params(RESPONSES[0], max(PSF_SIGMAS_PX), False, res, 0)
            except ConfigError as err:
                ap.error(f"--resolutions {res}: too small for the grid's {max(PSF_SIGMAS_PX)} px blur ({err})")
        return main_responses(args, provenance(args))
    prov = provenance(args)
    rows = []
    print("| scenario | seed | px | delta at truth | at range x(1-step) | x(1+step) | mean offset px | stations |")
    print("|---|---|---|---|---|---|---|---|")
    for scenario in args.scenarios:
        for res in args.resolutions:
            for seed in args.seeds:
                r = one_case(scenario, seed, res, args.num_images, args.work, args.stride, args.step)
                rows.append(r)
                lo, mid, hi = (r[f"range_x{1 + e:.4f}"]["delta"] for e in (-args.step, 0.0, args.step))
                pct = (lambda v: "-" if v is None else f"{100 * v:+.3f} %")
                print(f"| {scenario} | {seed} | {res} | {pct(mid)} | {pct(lo)} | {pct(hi)} | "
                      f"{r['offset_px_mean']:+.3f} | {r['stations']} |", flush=True)
                from envisat_pose.io import atomic_write_text

                atomic_write_text(args.out, json.dumps({"cases": rows, "argv": sys.argv[1:], "stride": args.stride,
                                                        "step": args.step, "provenance": prov}, indent=1))
    return 0


def main_responses(args, prov: dict) -> int:
    from envisat_pose.io import atomic_write_text

    print("| scenario | seed | px | response | PSF sigma px | blooming | delta stored | known response "
          "| estimated response | estimate |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    rows = []
    for scenario in args.scenarios:
        for res in args.resolutions:
            for seed in args.seeds:
                rows += responses_case(scenario, seed, res, args.num_images, args.work, args.stride)
                atomic_write_text(args.out, json.dumps({"looks": rows, "argv": sys.argv[1:], "stride": args.stride,
                                                        "provenance": prov}, indent=1))
    return 0


if __name__ == "__main__":
    from _common import run_main  # bench/_common.py, beside this script

    run_main(main)
