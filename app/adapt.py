"""`envisat adapt`: the verb over pipelines/adaptation/adapt.py: teach the detector your own frames (tracked cold,
pseudo-labelled at the smoothed track, recalibrated and optionally fine-tuned, tracked again), judged on a held-out
final part."""

from __future__ import annotations

import argparse

from envisat_pose.app.common import add_common, add_frame_inputs
from envisat_pose.config import InputError
from envisat_pose.out_dirs import check_out_dir
from envisat_pose.pipelines.runs.frames import open_source


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "adapt",
        help="adapt the detector to your own frames, with no labels: track, pseudo-label, fine-tune, track again",
        description="Track the frames cold, label the frames the tracker trusts (tracking, half-turn decided, "
        "tight covariance) at its smoothed estimate, their range corrected by the frames' own silhouette edges, "
        "recalibrate the detector on them (its covariance and apparent scale; --fine-tune to train it too) "
        "and track again. The final quarter is held out: if the adapted weights do worse there, the original ones "
        "are kept and the verb exits 1 saying why. Writes detector.safetensors and detector.json (only when "
        "adopted: a rejected rerun leaves an earlier adopted pair in --out as it was), report.json, before/ and "
        "after/ (the two track runs) into --out.",
    )
    add_frame_inputs(p)
    p.add_argument("--rounds", type=int, default=1, help="track-label-fine-tune-track rounds (default 1)")
    p.add_argument("--steps", type=int, help="fine-tune steps per round (default 60)")
    p.add_argument("--lr", type=float, help="fine-tune peak learning rate (default 5e-4)")
    p.add_argument("--fine-tune", choices=["none", "norm_heads", "all"],
                   help="what the fine-tune trains: none (default: the detector recalibrated on the labels only, "
                   "its covariance and apparent scale), norm_heads (the normalization layers and the heads), all")
    p.add_argument("--device", default="cpu", help="torch device of the fine-tune: cpu (default), cuda")
    add_common(p, out="output folder (created; an earlier run's outputs are replaced, its adopted weights only by "
               "adopted ones)", out_metavar="RUN_DIR",
               config="track config (orbit, filter, tracker; top-level keys)", weights=True,
               seed="seed of the fine-tune's crops, augmentation and batches (default 0)", flag_names=FLAGS)
    p.set_defaults(func=adapt_cli)


# the library's argument names -> this verb's flags (app/common.as_flags)
FLAGS = {"source": "--images", "rate_hz": "--rate-hz", "timestamps": "--timestamps", "bit_depth": "--bit-depth",
         "camera": "--camera", "rounds": "--rounds", "steps": "--steps", "lr": "--lr", "device": "--device",
         "params": "--fine-tune"}


def refuse_other_targets_weights(weights: str | None) -> None:
    """InputError (one line) for another target's keypoint detector: the track's own refusal pointed to a target
    file, which adapt takes none of. (In Python, AdaptConfig's TrackConfig refuses those weights when built, and
    AdaptConfig any target but ENVISAT.)"""
    import os

    from envisat_pose.perception.weights import read_header, trained_for

    theirs = trained_for(weights, read_header(weights)) if weights and os.path.isfile(weights) else None
    if theirs is not None:
        raise InputError(f"--weights {weights!r}: the keypoint detector of target {theirs.get('name')!r}, not "
                         "ENVISAT's; `envisat adapt` fine-tunes and recalibrates ENVISAT's corner detector only "
                         "(another target's is trained and calibrated with `envisat train --target` and `envisat "
                         "calibrate --target`)")


def adapt_cli(args: argparse.Namespace) -> int:
    import os
    import sys

    from envisat_pose.pipelines.adaptation.adapt import AdaptConfig, adapt
    from envisat_pose.pipelines.jobs import resolve_job

    if args.fine_tune in (None, "none") and (args.steps is not None or args.lr is not None):
        raise InputError("--steps and --lr set the fine-tune, which is off by default: add --fine-tune norm_heads "
                         "(or all)")
    check_out_dir(args.out)
    refuse_other_targets_weights(args.weights)
    source = open_source(args.images, args.rate_hz or 0.0, args.timestamps, args.bit_depth)
    track = resolve_job("track", args.scenario or source.scenario or "default", args.config,
                        rate_hz=args.rate_hz, weights=args.weights)
    fields = {"steps": args.steps, "lr": args.lr, "seed": args.seed, "params": args.fine_tune}
    cfg = AdaptConfig(track=track, rounds=args.rounds, device=args.device,
                      **{k: v for k, v in fields.items() if v is not None})
    report = adapt(cfg, source, args.out, camera=args.camera, progress=not args.quiet,
                   command=["envisat"] + list(getattr(args, "argv", [])))
    print(f"{args.images}: {report['source']['frames']} frames; held out from frame "
          f"{report['held_out_from_frame']}; {report['rounds'][-1]['labels']} pseudo-labelled frames")
    for name in ("before", "after"):
        f = report[name]
        if f is None:
            continue
        nis = "n/a" if f["mean_nis_per_dof"] is None else f"{f['mean_nis_per_dof']:.2f}"
        print(f"{name:>6}: held-out tracked {f['tracked_share']:.0%}, mean NIS/dof {nis}, pose stays tracked "
              f"from frame {f['stays_tracked_from']}")
    print(f"took {report['timing_s']['total']:.0f} s")
    if report.get("scale_note"):
        print(f"apparent scale: {report['scale_note']}")
    if not report["adopted"]:
        kept = (f"; the earlier adopted {os.path.join(args.out, 'detector.safetensors')} stays as it was"
                if report.get("earlier_weights_kept") else "")
        print(f"envisat adapt: kept the original weights: {report['reason']}{kept}", file=sys.stderr)
        return 1
    if report.get("removed_calibration"):  # a fine-tuned network: what it no longer carries, and how to measure it
        print(report["removed_calibration"])
    print(f"wrote {args.out}: detector.safetensors, detector.json, report.json, before/, after/")
    return 0
