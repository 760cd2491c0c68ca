"""What the verbs share: the common flags (--out, --config, --weights, --seed, --quiet; the recording's --spawn and
--connect; a dataset's --skip-damaged and the line naming what it left out) and the mapping of a library error's
argument names onto a verb's flags.

The library names its arguments and config fields in its errors ('out_dir ...', 'weights ...', '`rate_hz`'); a
verb lists which of them are its flags (`flag_names`, set on the parser with set_defaults) and the command line
(app/cli.py) prints the error with those names turned into the flags the user typed (`as_flags`).
"""

from __future__ import annotations

import argparse
import re

from envisat_pose.config import InputError
from envisat_pose.out_dirs import check_out_file

# library argument / field names -> flags, for every verb that adds the flag with add_common
COMMON_FLAGS = {"out": "--out", "out_dir": "--out", "config_path": "--config", "weights": "--weights",
                "seed": "--seed"}
# the measurement flags of estimate and montecarlo, by the config fields they set
MEASUREMENT_FLAGS = {"measurement.kind": "--measurements", "measurement.sigma_m": "--sigma-m",
                     "measurement.sigma_px": "--sigma-px", "measurement.sigma_range_m": "--sigma-range-m",
                     "measurement.max_markers": "--max-markers", "measurement.failure_prob": "--failure-prob",
                     "measurement.outages_s": "--outage", "measurement.rate_hz": "--rate-hz"}
# ... and for every verb (a damaged shard's hint names --skip-damaged on every verb that reads a dataset)
EVERY_VERB = {"skip_damaged": "--skip-damaged", "bf16": "--bf16"}


def add_common(p: argparse.ArgumentParser, *, out: str | None = None, out_default: str | None = None,
               out_metavar: str = "DIR", config: str | None = None, weights: bool = False, seed: str | None = None,
               quiet: bool = True, flag_names: dict[str, str] | None = None) -> None:
    """Add the common flags to a verb's parser: --out (help text `out`; required unless out_default), --config
    (help `config`), --weights (the detector's), --seed (help `seed`), --quiet; and record which library names
    are its flags (COMMON_FLAGS, then flag_names) for its errors (as_flags)."""
    if out is not None:
        p.add_argument("--out", required=out_default is None, default=out_default, metavar=out_metavar, help=out)
    if config is not None:
        p.add_argument("--config", metavar="FILE.toml", help=config)
    if weights:
        p.add_argument("--weights", metavar="W.safetensors",
                       help="detector weights (default: the shipped models/detector.safetensors)")
    if seed is not None:
        p.add_argument("--seed", type=int, help=seed)
    if quiet:
        p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(flag_names={**COMMON_FLAGS, **(flag_names or {})})


def add_bf16_argument(p: argparse.ArgumentParser) -> None:
    """--bf16: ENVISAT's corner detector runs its network in bfloat16 (DetectConfig.bf16)."""
    p.add_argument("--bf16", action="store_true", help="run ENVISAT's corner detector's network in bfloat16 (not "
                   "another target's keypoint detector): faster on CPUs with AVX512-BF16 or AMX, slower elsewhere; "
                   "accuracy beside float32 in bench/results/detector_bf16.json (default: float32)")


def add_recording_arguments(p: argparse.ArgumentParser) -> None:
    """--spawn / --connect URL: the recording streamed to a viewer instead of the output folder's recording.rrd."""
    g = p.add_mutually_exclusive_group()
    g.add_argument("--spawn", action="store_true", help="stream the recording to a new local Rerun viewer")
    g.add_argument("--connect", metavar="URL", help="stream the recording to a running viewer "
                   "(e.g. rerun+http://127.0.0.1:9876/proxy) instead of RUN_DIR/recording.rrd")


def add_skip_damaged_argument(p: argparse.ArgumentParser) -> None:
    """--skip-damaged, the same on every verb that reads a generated dataset (the check: shard_reader.checked_shards;
    its error's hint, shard_reader.skip_hint, names the flag through EVERY_VERB)."""
    p.add_argument("--skip-damaged", action="store_true",
                   help="go on without the shards that do not match the dataset's manifest.json (size, sha256, "
                   "samples), naming them (default: a damaged shard stops the run before any output)")


def skipped_line(skipped: list[str]) -> str:
    """The line a verb prints about the damaged shards --skip-damaged left out ('' when none)."""
    return f"skipped {len(skipped)} damaged shard(s): {', '.join(skipped)}" if skipped else ""


def recording_sink(args: argparse.Namespace) -> str | None:
    """The recording sink of the flags (Rerun's own examples' --spawn/--connect); None: the job's own file."""
    if getattr(args, "spawn", False):
        return "spawn"
    if getattr(args, "connect", None):
        return f"connect:{args.connect}"
    return None


_LEADING_NAME = re.compile(r"^(\w+)(?=[ :=]|$)")  # a name, not a path's first folder (data/x.pt) or a field (data.x)
_QUOTED_NAME = re.compile(r"`(\w+)`")


def as_flags(message: str, names: dict[str, str]) -> str:
    """A library error with its argument names as a verb's flags: the leading name ('src ...' -> '--images ...')
    and every `name` in backquotes that is one of `names` (others lose only their quotes)."""
    message = _LEADING_NAME.sub(lambda m: names.get(m.group(1), m.group(1)), message, count=1)
    return _QUOTED_NAME.sub(lambda m: names.get(m.group(1), m.group(1)), message)


def check_rrd_output(path: str) -> None:
    """--rrd must name a .rrd file that can be written (out_dirs.check_out_file): InputError before any work."""

    if not path.endswith(".rrd"):
        raise InputError(f"--rrd {path!r}: expected a path ending in .rrd")
    check_out_file(path, "--rrd")


def add_frame_inputs(p: argparse.ArgumentParser) -> None:
    """A user's frames, as `envisat track` and `envisat adapt` take them: --images, --rate-hz or --timestamps,
    --bit-depth, --camera, --scenario."""
    p.add_argument("--images", required=True, metavar="SRC", help="generate folder, image folder or video file")
    p.add_argument("--rate-hz", type=float, help="frame rate of an image folder or a video: frame k at k / R s")
    p.add_argument("--timestamps", metavar="FILE.csv", help="frame times of an image folder (columns file,t_s)")
    p.add_argument("--bit-depth", type=int, metavar="BITS", help="bits of the data in 16-bit image files: 8, 10, "
                   "12, 14 or 16 (default: the smallest of 10-16 that holds the sequence's maximum, reported)")
    p.add_argument("--camera", metavar="FILE.toml", help="intrinsics fx, fy, cx, cy (px), width, height, optional "
                   "distortion (default: the MJCF's chaser_cam, 1024 x 1024 px; a generate folder's at its size)")
    p.add_argument("--scenario", help="where the chaser's orbit and the target's dynamics come from (default: a "
                   "generate folder's own, else 'default')")


def init_error_line(scale: float) -> str:
    """The line `estimate` and `montecarlo` print for runs whose initial errors are not drawn from the filter's P0."""
    return f"each run started {scale:g} x P0's sigmas off (--init-error-scale); the filter was told P0"
