"""The contracts between stages (design.md, Contracts): dataclasses of numpy arrays, saved as .npz.

Stages exchange only these. `save` writes atomically and byte-reproducibly (envisat_pose.io.save_npz) after
checking the arrays; `load` checks keys, shapes, dtypes and finiteness, so a truncated, foreign or malformed
file is one InputError line naming the file and what is wrong, never a traceback. No pickle is ever read.

Shapes use symbolic sizes: N samples of a truth, F detection frames, R Monte Carlo runs, T filter steps.
"""

from __future__ import annotations

import dataclasses
import json
import zipfile
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from envisat_pose.config import InputError
from envisat_pose.io import NotAnNpz, open_npz, save_npz
from envisat_pose.status import STATUSES, has_estimate, legend_json

# A shard label's corruption severities, level 0..3 (label['corruption']['levels'][kind] is one of them): the
# factory draws them (datagen/corrupt.py), the detector's evaluation groups by them (perception/evaluate.py)
SEVERITIES = ("none", "low", "medium", "high")

# (kind, shape, rule): kind 'f' float64, 'b' bool, 'i' int64, 's' text; shape of ints (fixed) and names (shared sizes);
# rule 'finite' (every value finite), 'finite_where_visible' (finite where the `visible` mask is true), None.
_Spec = tuple[str, tuple, str | None]


class ContractError(InputError):
    """A file that does not hold the contract it should: the message names the file and the problem."""


def _check_array(path: str, name: str, a: np.ndarray, spec: _Spec, sizes: dict) -> np.ndarray:
    kind, shape, rule = spec
    if kind == "f" and a.dtype.kind not in "fiu" or kind == "b" and a.dtype.kind != "b" \
            or kind == "i" and a.dtype.kind not in "iu" or kind == "s" and a.dtype.kind != "U":
        want = {"f": "floating-point", "b": "boolean", "i": "integer", "s": "text"}[kind]
        raise ContractError(f"{path}: '{name}' has dtype {a.dtype}, expected {want}")
    if a.ndim != len(shape):
        raise ContractError(f"{path}: '{name}' has shape {a.shape}, expected {len(shape)} dimensions "
                            f"({', '.join(str(s) for s in shape)})")
    for axis, (dim, want) in enumerate(zip(a.shape, shape)):
        if isinstance(want, str):
            have = sizes.setdefault(want, dim)
            if have != dim:
                raise ContractError(f"{path}: '{name}' has shape {a.shape}: axis {axis} is {dim}, but {want} = {have} "
                                    "in the arrays before it")
        elif dim != want:
            raise ContractError(f"{path}: '{name}' has shape {a.shape}, expected size {want} on axis {axis}")
    if kind == "s":
        return np.asarray(a)
    out = {"f": np.float64, "b": np.bool_, "i": np.int64}[kind]
    return np.asarray(a, dtype=out)


def _check_finite(path: str, name: str, a: np.ndarray, rule: str | None, arrays: dict) -> None:
    if rule is None:
        return
    if rule == "finite_or_absent" and np.isnan(a).all():  # a quantity the producer did not have (all NaN)
        return
    if rule == "finite_where_estimate":  # NaN allowed on rows whose status says they hold no estimate
        status = arrays.get("status")
        ok = np.isfinite(a)
        if status is not None:
            ok |= ~has_estimate(status).reshape(status.shape + (1,) * (a.ndim - status.ndim))
    elif rule in ("finite", "finite_or_absent"):
        ok = np.isfinite(a)
    else:  # finite where the corner is visible
        vis = arrays["visible"]
        ok = np.isfinite(a) | ~vis.reshape(vis.shape + (1,) * (a.ndim - vis.ndim))
    if not ok.all():
        first = tuple(int(i) for i in np.argwhere(~ok)[0])
        raise ContractError(f"{path}: '{name}' holds non-finite values (first at index {first})")


class _Contract:
    """Shared save/load of the contract dataclasses below (each defines SPEC and KIND)."""

    SPEC: ClassVar[dict[str, _Spec]]
    KIND: ClassVar[str]
    OPTIONAL: ClassVar[dict[str, _Spec]] = {}  # arrays a file may hold (None in the dataclass when absent)

    def arrays(self) -> dict:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)
                if not (f.name in self.OPTIONAL and getattr(self, f.name) is None)}

    @classmethod
    def validated(cls, data: dict, path: str = "<memory>"):
        """Check and convert plain arrays (dtype, shape, finiteness) into the contract; ContractError if not."""
        missing = [k for k in cls.SPEC if k not in data] + (["config_json"] if "config_json" not in data else [])
        if missing:
            raise ContractError(f"{path}: not a {cls.KIND} file: missing {', '.join(repr(m) for m in missing)}")
        sizes: dict = {}
        arrays = {}
        specs = cls.SPEC | {k: v for k, v in cls.OPTIONAL.items() if data.get(k) is not None}
        for name in sorted(specs, key=lambda k: k not in cls.OPTIONAL):  # optional arrays (status) first
            arrays[name] = _check_array(path, name, np.asarray(data[name]), specs[name], sizes)
        for name, spec in specs.items():
            _check_finite(path, name, arrays[name], spec[2], arrays)
        text = data["config_json"]
        text = str(text.item() if isinstance(text, np.ndarray) else text)
        try:
            if not isinstance(json.loads(text), dict):
                raise ValueError("not a JSON object")
        except ValueError as err:
            raise ContractError(f"{path}: 'config_json' is not a JSON object ({err})") from None
        arrays["config_json"] = text
        obj = cls(**arrays)
        obj.check(path)
        return obj

    def check(self, path: str) -> None:
        """Rules across arrays beyond shapes (overridden where a contract has them)."""

    def save(self, path: str) -> None:
        """Check the arrays, then write an .npz atomically; the same contents give the same bytes."""
        type(self).validated(self.arrays(), path)
        save_npz(path, {**self.arrays(), "config_json": np.array(self.config_json)} | self.extras())

    def extras(self) -> dict:
        """Members written beside the arrays (overridden: est.npz's status legend)."""
        return {}

    @classmethod
    def load(cls, path: str, field: str | None = None):
        """Read and check a file; ContractError (one line, naming the file) when it is not this contract, led by
        `field` where given: the argument that named the file ("truth_path 'run.npz': no such file")."""
        where = path if field is None else f"{field} {path!r}"
        try:
            with open_npz(path) as z:
                data = {k: z[k] for k in z.files}
        except NotAnNpz:
            raise ContractError(f"{where}: not a {cls.KIND} .npz file (not a zip archive)") from None
        except FileNotFoundError:
            raise ContractError(f"{where}: no such file") from None
        except IsADirectoryError:
            raise ContractError(f"{where}: is a folder, expected a {cls.KIND} .npz file") from None
        except (OSError, ValueError, EOFError, zipfile.BadZipFile, KeyError) as err:
            # truncated zips, foreign formats, object arrays (refused: no pickles) all end here
            raise ContractError(f"{where}: cannot be read as a {cls.KIND} .npz file ({type(err).__name__}: "
                                f"{err})") from None
        return cls.validated(data, where)

    @property
    def config(self) -> dict:
        """config_json parsed."""
        return json.loads(self.config_json)


@dataclass
class TruthTrajectory(_Contract):
    """A simulated truth (`envisat simulate --out run.npz`), N samples.

    t_s: (N,) s, increasing. x: (N, 12) = (rho_C_m, rhodot_C_m_s, p_mrp with |p| <= 1, w_r_T_rad_s), the paper's
    state (reference sheet, section 3). chaser_r_m, chaser_rdot_m_s, chaser_theta_rad, chaser_thetadot_rad_s:
    (N,) the chaser's polar orbit (m, m/s, rad, rad/s).
    corners_C_m: (N, K, 3) the target's K keypoints (ENVISAT: K = 8, corners A-H) relative to the chaser, in C, m:
    MuJoCo's keypoint sites (the target file's, config_json's target.file). visible: (N, K) bool, ENVISAT: the exact
    face test of the box from the chaser; another target: exact ray casts through its geoms (Target.truth_visible).
    corners_px: (N, K, 2) MuJoCo's keypoint sites projected through MuJoCo's chaser camera, px (OpenCV
    convention: pixel centres at integer coordinates); in_frame: (N, K) bool, in front of the camera and
    inside the image.
    config_json: the full validated scenario config as JSON.
    """

    t_s: np.ndarray
    x: np.ndarray
    chaser_r_m: np.ndarray
    chaser_rdot_m_s: np.ndarray
    chaser_theta_rad: np.ndarray
    chaser_thetadot_rad_s: np.ndarray
    corners_C_m: np.ndarray
    visible: np.ndarray
    corners_px: np.ndarray
    in_frame: np.ndarray
    config_json: str

    KIND: ClassVar[str] = "truth trajectory"
    SPEC: ClassVar[dict[str, _Spec]] = {
        "t_s": ("f", ("N",), "finite"),
        "x": ("f", ("N", 12), "finite"),
        "chaser_r_m": ("f", ("N",), "finite"),
        "chaser_rdot_m_s": ("f", ("N",), "finite"),
        "chaser_theta_rad": ("f", ("N",), "finite"),
        "chaser_thetadot_rad_s": ("f", ("N",), "finite"),
        "corners_C_m": ("f", ("N", "K", 3), "finite"),
        "visible": ("b", ("N", "K"), None),
        "corners_px": ("f", ("N", "K", 2), "finite"),
        "in_frame": ("b", ("N", "K"), None),
    }

    def check(self, path: str) -> None:
        if len(self.t_s) < 1:
            raise ContractError(f"{path}: the truth trajectory has no samples")
        if len(self.t_s) > 1 and not np.all(np.diff(self.t_s) > 0):
            raise ContractError(f"{path}: 't_s' is not strictly increasing")


@dataclass
class Detections(_Contract):
    """What perception hands the filter, F frames (design.md, Detections).

    K keypoints: ENVISAT's corners A-H (8), or another target's keypoints in its file's order (a tracker's
    det.npz of that target, `envisat track --target` / `envisat run --target`).
    t_s: (F,) frame times, s. corners_px: (F, K, 2) the keypoints in the full image, px (OpenCV convention).
    cov_px: (F, K, 2, 2) calibrated pixel covariance, px^2 (the filter's R). confidence: (F, K) in [0, 1].
    visible: (F, K) bool, the keypoint was found. Positions and covariances must be finite where visible.
    config_json: what produced them, as JSON.
    Optional (`envisat detect` writes them; None where a file lacks them): key (F,) str, the frame's sample key;
    alt_corners_px (F, K, 2) px, ENVISAT's corner network's half-turn alternative naming (A<->C, B<->D, E<->G, F<->H; NaN where none);
    alt_probability (F,) its probability; ambiguous (F,) bool, the naming could not be decided.
    """

    t_s: np.ndarray
    corners_px: np.ndarray
    cov_px: np.ndarray
    confidence: np.ndarray
    visible: np.ndarray
    config_json: str
    key: np.ndarray | None = None
    alt_corners_px: np.ndarray | None = None
    alt_probability: np.ndarray | None = None
    ambiguous: np.ndarray | None = None

    KIND: ClassVar[str] = "detections"
    SPEC: ClassVar[dict[str, _Spec]] = {
        "visible": ("b", ("F", "K"), None),
        "t_s": ("f", ("F",), "finite"),
        "corners_px": ("f", ("F", "K", 2), "finite_where_visible"),
        "cov_px": ("f", ("F", "K", 2, 2), "finite_where_visible"),
        "confidence": ("f", ("F", "K"), "finite"),
    }
    OPTIONAL: ClassVar[dict[str, _Spec]] = {
        "key": ("s", ("F",), None), "alt_corners_px": ("f", ("F", "K", 2), None),
        "alt_probability": ("f", ("F",), None), "ambiguous": ("b", ("F",), None),
    }

    def check(self, path: str) -> None:
        if np.any((self.confidence < 0) | (self.confidence > 1)):
            raise ContractError(f"{path}: 'confidence' has values outside [0, 1]")


@dataclass
class KeypointDetections(_Contract):
    """What another target's keypoint detector found (`envisat detect --target FILE.xml`), F frames of its K
    keypoints, named as the weights name them (keypoint_names, the target file's order).

    key: (F,) the frame's sample key. t_s: (F,) frame times, s. keypoints_px: (F, K, 2) full image, px (OpenCV
    convention; each channel's peak, found or not). score: (F, K) the heatmap's peak in [0, 1]. visible_prob:
    (F, K) the network's probability that the keypoint is visible, in [0, 1]; visible: (F, K) bool, visible_prob at
    least the detector's threshold. keypoint_names: (K,) str. crop_px: (F, 3) (x0, y0, side) of the pass that gave
    the positions. config_json: the weights, their target (name, sha256), the data.
    Optional (`envisat detect --target` writes it; None where a file lacks it): cov_px (F, K, 2, 2) px^2, the
    calibrated pixel covariance of each keypoint (the filter's R: sigma_k^2 I from `envisat calibrate --target`),
    NaN for a keypoint the weights carry no calibration of; a finite one is symmetric positive definite.
    """

    key: np.ndarray
    t_s: np.ndarray
    keypoints_px: np.ndarray
    score: np.ndarray
    visible_prob: np.ndarray
    visible: np.ndarray
    keypoint_names: np.ndarray
    crop_px: np.ndarray
    config_json: str
    cov_px: np.ndarray | None = None

    KIND: ClassVar[str] = "keypoint detections"
    SPEC: ClassVar[dict[str, _Spec]] = {
        "key": ("s", ("F",), None),
        "t_s": ("f", ("F",), "finite"),
        "keypoints_px": ("f", ("F", "K", 2), "finite"),
        "score": ("f", ("F", "K"), "finite"),
        "visible_prob": ("f", ("F", "K"), "finite"),
        "visible": ("b", ("F", "K"), None),
        "keypoint_names": ("s", ("K",), None),
        "crop_px": ("f", ("F", 3), "finite"),
    }
    OPTIONAL: ClassVar[dict[str, _Spec]] = {"cov_px": ("f", ("F", "K", 2, 2), None)}

    def check(self, path: str) -> None:
        for name in ("score", "visible_prob"):
            a = getattr(self, name)
            if np.any((a < 0) | (a > 1)):
                raise ContractError(f"{path}: '{name}' has values outside [0, 1]")
        if self.cov_px is not None:
            c = self.cov_px
            given = np.isfinite(c).all(axis=(-2, -1))
            symmetric = np.abs(c[..., 0, 1] - c[..., 1, 0]) <= 1e-9 * np.abs(c).max(axis=(-2, -1))
            pd = (c[..., 0, 0] > 0) & (c[..., 0, 0] * c[..., 1, 1] - c[..., 0, 1] * c[..., 1, 0] > 0)
            bad = ~np.isnan(c).all(axis=(-2, -1)) & ~(given & symmetric & pd)
            if bad.any():
                first = tuple(int(i) for i in np.argwhere(bad)[0])
                raise ContractError(f"{path}: 'cov_px' at {first} is neither all NaN nor a symmetric positive "
                                    "definite 2x2")


@dataclass
class Estimates(_Contract):
    """What the filter hands analysis (`envisat estimate --out est.npz`), R runs over T steps.

    t_s: (T,) s. x_true: (R, T, 12) the truth on the filter's grid; x_hat: (R, T, 12) posterior means; P:
    (R, T, 12, 12) posterior covariances (units of the state, squared). n_meas: (R, T) corners used per step.
    nis: (R, T) normalized innovation squared (0 without measurement); nis_dof: (R, T) its degrees of freedom
    (measured components used). diverged: (R,) bool, one meaning everywhere: the run's estimate was flagged
    inconsistent by a monitor (the filter's windowed NIS, with a truth the NEES window; for the tracker's runs,
    any frame it declared lost). Whether a run met a truth's tolerances is a score, not this flag (the closed
    loop's est.npz stores it beside as `settled`).
    config_json: the estimate config, the truth's source and config, as JSON.
    status: optional (R, T) the tracker's status code per row (envisat_pose.status; a file stores its legend as
    JSON in `status_legend`): x_hat and P are NaN on rows whose status holds no estimate (acquiring, lost) and
    finite on the others; absent (None), every row is an estimate.
    judged: optional (R,) bool, whether the divergence rule judged the run (`envisat estimate`: False for a run
    unflagged that ended before the monitors were armed, its diverged False meaning "not judged", never "not
    diverged"; a flagged run is judged). Absent (None: a file before the field, or the tracker's runs, whose
    diverged is a loss seen over every frame), every run counts as judged (judged_runs).
    """

    t_s: np.ndarray
    x_true: np.ndarray
    x_hat: np.ndarray
    P: np.ndarray
    n_meas: np.ndarray
    nis: np.ndarray
    nis_dof: np.ndarray
    diverged: np.ndarray
    config_json: str
    status: np.ndarray | None = None
    judged: np.ndarray | None = None

    KIND: ClassVar[str] = "estimates"
    OPTIONAL: ClassVar[dict[str, _Spec]] = {"status": ("i", ("R", "T"), None), "judged": ("b", ("R",), None)}
    SPEC: ClassVar[dict[str, _Spec]] = {
        "t_s": ("f", ("T",), "finite"),
        "x_true": ("f", ("R", "T", 12), "finite_or_absent"),
        "x_hat": ("f", ("R", "T", 12), "finite_where_estimate"),
        "P": ("f", ("R", "T", 12, 12), "finite_where_estimate"),
        "n_meas": ("i", ("R", "T"), None),
        "nis": ("f", ("R", "T"), "finite"),
        "nis_dof": ("i", ("R", "T"), None),
        "diverged": ("b", ("R",), None),
    }

    def check(self, path: str) -> None:
        if self.status is not None:
            if np.any((self.status < 0) | (self.status >= len(STATUSES))):
                raise ContractError(f"{path}: 'status' holds codes outside 0..{len(STATUSES) - 1} "
                                    "(envisat_pose.status)")
        if self.judged is not None and np.any(self.diverged & ~self.judged):
            first = int(np.flatnonzero(self.diverged & ~self.judged)[0])
            raise ContractError(f"{path}: run {first} is 'diverged' but not 'judged' (a flagged run was judged)")

    def judged_runs(self) -> np.ndarray:
        """(R,) bool: the runs the divergence rule judged (`judged`; all of them in a file without it)."""
        return np.ones(len(self.diverged), bool) if self.judged is None else np.asarray(self.judged, bool)

    def extras(self) -> dict:
        if self.status is None:
            return {}

        return {"status_legend": np.array(legend_json())}
