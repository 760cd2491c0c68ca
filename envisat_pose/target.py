"""The target: one spacecraft, read once from its MJCF file into one `Target` that every layer takes.

A target file's worldbody holds one body named `target` with its <inertial> (mass, inertia about the centre of
mass at the body's origin; without one, what MuJoCo computes from the geoms, their CoM at the origin), its geoms
and materials, and its keypoints as the body's sites `kp_<name>` in file order (a file with none takes its
`corner_<name>` sites: models/envisat.xml's corners A-H). The body frame of the
file is the frame T of the labels, the truth and the filter. The file is read by MuJoCo itself (MjSpec), so its own
<compiler> (angle unit, eulerseq, meshdir, texturedir), defaults and assets give the shape MuJoCo gives it alone;
child bodies are fused into it as MuJoCo fuses static bodies, joints latched (envisat_pose/target_fused.py).
This module holds the Target and its entry points (load_target, cached per file); the file is read and checked in
target_reader.py, and the fast visibility table is target_visibility.py's (both re-exported here).

ENVISAT (models/envisat.xml) is the default target. Whether a target is ENVISAT is asked here only
(`Target.is_default`, the `require_default*` checks of the verbs whose detector or filter know ENVISAT alone,
and `require_weights_target`, whether a detector's weights were trained for the target a verb is given):
the architecture test refuses the question anywhere else.
"""

from __future__ import annotations

import filecmp
import functools
import os
import warnings
from dataclasses import dataclass

import numpy as np

from envisat_pose.config import ConfigError, InputError
from envisat_pose.config_errors import TargetFileWarning
from envisat_pose.geometry import model_path, visible_corners
from envisat_pose.shard_reader import load_dataset_manifest
from envisat_pose.target_assets import named_files
from envisat_pose.target_mesh import BodyMesh, TriangleMesh, feature_edges
from envisat_pose.target_rays import ray_hits_m
from envisat_pose.target_reader import RENDERED_GROUPS, TargetGeom, read_target_fields
from envisat_pose.target_shape import Symmetry, mirror_perm, skeleton, symmetries
from envisat_pose.target_visibility import SEEN_CHECK_DIRECTIONS, VisibilityTable, build_visibility_table, never_seen

__all__ = [
    "APPENDAGE_GROUP", "DEFAULT_TARGET", "RAY_ABS_TOL_M", "RENDERED_GROUPS", "Target", "TargetGeom", "VisibilityTable",
    "default_target", "envisat_only", "is_default_file", "load_target", "other_target", "require_envisat",
    "require_envisat_dataset", "require_weights_target", "resolve_target_path",
]

DEFAULT_TARGET = "models/envisat.xml"  # the default `target` of every config (the package's file)
APPENDAGE_GROUP = 4  # geom group of the clutter the `appendages` switch draws (models/envisat.xml)
RAY_ABS_TOL_M = 1e-4  # a surface this much nearer than a keypoint (plus 1e-6 of its range) does not hide it


@dataclass(frozen=True, eq=False)
class Target:
    """A checked target file, read once.

    name: the file's model name (<mujoco model=...>) or its stem. path: absolute. sha256: of the file's bytes and
    of the files it names (target_assets.target_sha256).
    keypoint_names (K,), keypoint_sites (K,) their MJCF site names; keypoints_T_m (K, 3) in T, m. mass_kg;
    inertia_T_kg_m2 (3, 3) about the CoM in T. reach_m: the farthest point of its surface from the CoM. geoms:
    (G,) TargetGeom, file order. surface: the triangles of every geom in T (target_mesh.BodyMesh). own_scene: the
    file holds the factory's scene (target_file.SCENE_NAMES), so it is rendered as it is. latched_joints: the
    file's joints in the target's tree, latched at their reference pose (target_fused.py: the target is one rigid
    body). Derived on first use: skeleton, symmetries.
    """

    name: str
    path: str
    sha256: str
    keypoint_names: tuple[str, ...]
    keypoint_sites: tuple[str, ...]
    keypoints_T_m: np.ndarray
    mass_kg: float
    inertia_T_kg_m2: np.ndarray
    reach_m: float
    geoms: tuple[TargetGeom, ...]
    surface: BodyMesh
    own_scene: bool
    latched_joints: tuple[str, ...] = ()

    @functools.cached_property
    def skeleton(self) -> tuple[tuple[int, int], ...]:
        """Keypoint pairs (i, j), i < j, joined along the drawn surface's sharp edges, a keypoint no edge joins to
        its nearest (target_shape.skeleton); computed on first use."""
        points, edges = feature_edges(self.mesh())
        return skeleton(self.keypoints_T_m, points, edges, self.reach_m)

    @functools.cached_property
    def symmetries(self) -> tuple[Symmetry, ...]:
        """The rotations about the CoM that map the keypoint set onto itself, with whether the drawn shape and its
        materials keep each (target_shape.symmetries); computed on first use (~0.3 s for ENVISAT)."""
        return symmetries(self.keypoints_T_m, self.mesh(), self._drawn_face_rgb(), self.reach_m)

    @functools.cached_property
    def mirror_perm(self) -> tuple[int, ...] | None:
        """The keypoints' permutation under a mirror symmetry that the drawn shape and its materials keep (what a
        left-right flipped image relabels: YOLO's flip_idx), or None where the target is chiral (ENVISAT: its
        materials break its box's mirrors); target_shape.mirror_perm, computed on first use."""
        perm = mirror_perm(self.keypoints_T_m, self.mesh(), self._drawn_face_rgb(), self.reach_m)
        return None if perm is None else tuple(int(k) for k in perm)

    def _drawn_face_rgb(self) -> np.ndarray:
        """(F, 3) the colour of each triangle of the drawn surface (mesh())."""
        drawn = self.drawn()
        return np.array([self.geoms[g].rgb for g in self.surface.face_geom[drawn[self.surface.face_geom]]],
                        float).reshape(-1, 3)

    @property
    def is_default(self) -> bool:
        """The package's ENVISAT (the default target)."""
        return os.path.realpath(self.path) == os.path.realpath(model_path())

    @property
    def labels_name_keypoints(self) -> bool:
        """Whether a label names its keypoints (keypoint_names, keypoints_px): every target's but the default's,
        whose labels keep the shard contract's corners_px with A-H implied."""
        return not self.is_default

    @property
    def keypoint_detector(self) -> bool:
        """Whether its detector is a keypoint network (`envisat train --target`) and its tracker names keypoints
        by the target's own symmetries: every target's but the default's, whose detector is the corner network
        that names A-H by fitting its box (pipelines/tracking/namings.py)."""
        return not self.is_default

    @property
    def num_keypoints(self) -> int:
        return len(self.keypoint_names)

    def record(self, given: str) -> dict:
        """What a dataset's manifest records of its target: the path as given, the name, sha256, keypoints."""
        return {"file": given, "name": self.name, "sha256": self.sha256, "keypoint_names": list(self.keypoint_names)}

    def drawn(self, appendages: bool = False) -> np.ndarray:
        """(G,) bool: the geoms the factory draws (RENDERED_GROUPS, and APPENDAGE_GROUP with `appendages`; shown)."""
        groups = set(RENDERED_GROUPS) | ({APPENDAGE_GROUP} if appendages else set())
        return np.array([g.group in groups and g.shown for g in self.geoms], bool)

    def occluding(self, appendages: bool = False) -> np.ndarray:
        """(G,) bool: the drawn geoms that hide keypoints, the opaque ones (TargetGeom.opaque). MuJoCo draws a geom
        of alpha below 1 in its transparent pass, which the factory makes additive (for the Earth): its light is
        added over what lies behind, which the image keeps whole (a keypoint behind a veil of any alpha below 1
        shows at its full contrast), so such a geom hides none."""
        return self.drawn(appendages) & np.array([g.opaque for g in self.geoms], bool)

    def mesh(self, appendages: bool = False) -> TriangleMesh:
        """The drawn surface in T (drawn)."""
        return self.surface.select(self.drawn(appendages))

    def visible_from(self, c_T_m: np.ndarray, appendages: bool = False) -> np.ndarray:
        """Exact visibility of each keypoint from each point c_T_m (..., 3) in T: the ray from it to the keypoint
        meets no opaque drawn geom of the target before it (occluding; MuJoCo's own ray-geom intersections, less
        RAY_ABS_TOL_M plus 1e-6 of the range). The one rule of the labels, the truth and the filters' table.
        (..., K) bool."""
        c_T = np.asarray(c_T_m, float)
        hits = ray_hits_m(self.path, self.sha256, c_T, self.keypoints_T_m, self.occluding(appendages))
        rng = np.linalg.norm(self.keypoints_T_m - c_T[..., None, :], axis=-1)
        return hits >= rng - (RAY_ABS_TOL_M + 1e-6 * rng)

    def visible(self, R_K_from_T: np.ndarray, t_K_from_T_m: np.ndarray, appendages: bool = False) -> np.ndarray:
        """Exact visibility of each keypoint from the camera at pose (R_K_from_T (3, 3), t_K_from_T_m (3,)):
        visible_from the camera's centre, and in front of the camera. Not the image bounds (labels.in_frame).
        (K,) bool."""
        R = np.asarray(R_K_from_T, float)
        t = np.asarray(t_K_from_T_m, float)
        z = self.keypoints_T_m @ R[2] + t[2]
        return self.visible_from(-R.T @ t, appendages) & (z > 0)

    def visibility_table(self, appendages: bool = False) -> VisibilityTable:
        """The fast form of `visible_from` for a filter's visibility check (VisibilityTable): exact visibility
        from TABLE_DIRECTIONS directions at TABLE_RANGES_REACHES x reach, widened to the nearest directions, looked
        up by the nearest range and direction (built once per target and process, 0.2-0.5 s: build_visibility_table)."""
        return _table(self.path, self.sha256, bool(appendages))

    @property
    def filter_visibility(self) -> VisibilityTable | None:
        """What a filter predicts visibility with: None for the default target (the box's face rule, exact for
        ENVISAT's box without its array, which the fused kernels hold), the fast table for any other."""
        return None if self.is_default else self.visibility_table()

    def truth_visible(self, c_T_m: np.ndarray) -> np.ndarray:
        """The keypoints the camera at c_T_m (N, 3) in T sees, as a truth file records them, (N, K) bool:
        visible_from each point; the default target keeps the box's face rule (geometry.visible_corners: the
        seed paper's markers, which its Monte Carlo figures are pinned to; it ignores the array's shadow on the
        box, which the face rule cannot see)."""
        c = np.asarray(c_T_m, float).reshape(-1, 3)
        if self.is_default:
            return visible_corners(c)
        return self.visible_from(c)


@functools.lru_cache(maxsize=16)
def _table(path: str, sha256: str, appendages: bool) -> VisibilityTable:
    return build_visibility_table(load_target(path), appendages)


# ---------------------------------------------------------------- loading: the file a value names, read once


def resolve_target_path(given: str) -> str:
    """The file a `target` value names: DEFAULT_TARGET is the package's models/envisat.xml (ENVISAT_MODEL
    overrides it; a different file of that relative name in the working folder gets a warning saying how to name
    it: it is the default's text, so it cannot mean that file); any other path is taken as it is (relative to the working folder), or, when no such file
    exists and it starts with 'models/', the package's models folder."""
    if given == DEFAULT_TARGET:
        packaged = os.path.abspath(model_path())
        if os.path.isfile(given) and not filecmp.cmp(given, packaged, shallow=False):
            warnings.warn(f"target {given!r} is the packaged ENVISAT; the other file of that name in this folder is "
                          f"not used: give it as {os.path.join('.', given)!r}", stacklevel=2)
        return packaged
    if not os.path.exists(given) and given.startswith("models/"):
        packaged = os.path.join(os.path.dirname(model_path()), given[len("models/"):])
        if os.path.exists(packaged):
            return os.path.abspath(packaged)
    return os.path.abspath(given)


class _Naming:
    """How a caller names the file (`field`, `given`: its errors' words; `named`: its warnings', by default
    "target 'FILE'"), left out of _load's cache key: the same file named two ways is one load, its warnings said
    once."""

    def __init__(self, field: str, given: str, named: str | None = None):
        self.field, self.given, self.named = field, given, named or f"target {given!r}"

    def __eq__(self, other) -> bool:
        return isinstance(other, _Naming)

    def __hash__(self) -> int:
        return 0


@functools.lru_cache(maxsize=16)
def _load(path: str, stamps: tuple, naming: _Naming) -> Target:
    target = Target(**read_target_fields(path, naming.field, naming.given, naming.named))
    hidden = [] if target.is_default else never_seen(target)
    if hidden:  # said once per file, as the latched joints (the load is cached)
        warnings.warn(f"{naming.named}: keypoint site(s) {', '.join(map(repr, hidden))} hidden from each of "
                      f"{SEEN_CHECK_DIRECTIONS} view directions (inside or behind an opaque geom): no view labels "
                      "it visible, so the detector cannot learn it nor calibration measure it; put it on the "
                      "drawn surface", TargetFileWarning, stacklevel=3)  # load_target's caller
    return target


def load_target(given: str = DEFAULT_TARGET, field: str = "target", named: str | None = None) -> Target:
    """Returns a Target: the checked target of a config's `target` value, read once (its keypoints in T, m, its
    mass and inertia, its surface, sha256: class Target). given: a path; DEFAULT_TARGET is the package's ENVISAT;
    named: how its warnings name the file where it comes from elsewhere than `field`, a truth file's record).
    ConfigError naming `field`, the value and what was expected: no such file, a file MuJoCo cannot read or
    compile, no body 'target' (its child bodies are read fused, its joints latched: target_fused.py), a bad
    inertia (zero mass, not positive definite, the triangle inequality; stated by an <inertial>, or else MuJoCo's
    from the geoms and child bodies), the CoM off the body's origin, fewer than 4 keypoint sites, no geom the
    factory draws (RENDERED_GROUPS), a keypoint farther than KEYPOINT_MAX_SURFACE_DISTANCE_M from the drawn
    surface. Cached per file, size and modification time, its named files' too (target_assets.named_files)."""
    path = resolve_target_path(given)
    if not os.path.isfile(path) or not path.endswith(".xml"):  # MuJoCo picks its reader by the name's ending
        raise ConfigError(field, given, "an MJCF file (no such file)" if not os.path.isfile(path) else
                          "an MJCF file whose name ends in .xml (MuJoCo reads a model file by its ending, .xml alone "
                          "as MJCF: copy or link it so)")
    files = [f for f in (path, *named_files(path)) if os.path.isfile(f)]
    stamps = tuple((os.stat(f).st_mtime_ns, os.stat(f).st_size) for f in files)
    return _load(path, stamps, _Naming(field, given, named))


def is_default_file(given: str) -> bool:
    """Whether a `target` value names the default target's file (DEFAULT_TARGET or its path), read without
    MuJoCo: a truth of ENVISAT is estimated with the filter's own default model."""
    return given == DEFAULT_TARGET or os.path.realpath(resolve_target_path(given)) == os.path.realpath(model_path())


def other_target(given: str | None) -> str | None:
    """A `--target` value naming another target than ENVISAT (whose detector is the corner network), or None when
    none is given or it names ENVISAT's file: the verbs that train or run another target's keypoint detector."""
    return None if given is None or is_default_file(given) else given


def default_target() -> Target:
    """ENVISAT, the default target (models/envisat.xml)."""
    return load_target(DEFAULT_TARGET)


# ---------------------------------------------------------------- the verbs that know the default target alone


_OTHER_TARGET_WAY = {  # what a verb that met another target's file or dataset does with it instead
    "train": "another target's keypoint detector trains on frames it renders, without --data: `envisat train "
             "--target {file} --out RUN_DIR`",
    "detect": "another target's dataset: give its file, `--target {file}`",
    "evaluate": "another target's dataset: give its file, `--target {file}`",
    "calibrate": "another target's dataset: give its file, `--target {file}`",
    "adapt": "`envisat adapt` knows ENVISAT only: track another target with `envisat track --target {file} --weights "
             "W`",
}


def envisat_only(verb: str, file: str = "FILE.xml") -> str:
    """The reason a verb on ENVISAT's detector gives for refusing another target, and its way on (file: that
    target's file where it is known)."""
    way = _OTHER_TARGET_WAY.get(verb, "another target's images and labels come from `envisat generate --target`")
    return (f"ENVISAT ({DEFAULT_TARGET}): `envisat {verb}` and the detector know ENVISAT's corners A-H only; "
            + way.format(file=file))


def require_envisat(given: str, field: str, verb: str) -> None:
    """ConfigError unless the `target` value `given` names ENVISAT: the detector and the verbs built on it (track,
    run, adapt, train, detect) know ENVISAT only."""
    if given != DEFAULT_TARGET and not load_target(given, field).is_default:
        raise ConfigError(field, given, envisat_only(verb, given))


def require_envisat_dataset(folder: str, field: str, verb: str) -> None:
    """ConfigError unless the dataset in `folder` (its manifest.json) shows ENVISAT: its config's `target` is
    ENVISAT's (a dataset written before targets had none: ENVISAT). A missing folder, or one without a manifest,
    passes (the verb reports it); InputError naming the field when the manifest is not a dataset's."""
    manifest = load_dataset_manifest(folder, field, required=False) if os.path.isdir(folder) else None
    if manifest is None:
        return
    record = manifest.get("target") or {}
    given = (manifest.get("config") or {}).get("target", DEFAULT_TARGET)
    if given != DEFAULT_TARGET and (record.get("name") != default_target().name or
                                    record.get("keypoint_names") != list(default_target().keypoint_names)):
        raise ConfigError(field, folder, envisat_only(verb, given) + f"; this dataset's target is {given!r}")


def require_weights_target(weights: str, trained_for: dict | None, given: str, field: str = "weights") -> None:
    """InputError, one line naming the weights, their target and the target `given` (DEFAULT_TARGET: ENVISAT),
    unless they fit it: trained_for None (ENVISAT's corner detector) fits ENVISAT only, trained_for {'name',
    'sha256', ...} (another target's keypoint detector, its weights' metadata) only a file with that sha256."""
    if trained_for is None:
        if is_default_file(given):
            return
        t = load_target(given)
        raise InputError(f"{field} {weights!r}: ENVISAT's corner detector ({DEFAULT_TARGET}), not a detector of "
                         f"target {t.name!r} ({given}, sha256 {t.sha256[:12]}): give the weights `envisat train "
                         f"--target {given}` wrote")
    theirs = f"target {trained_for.get('name')!r} (sha256 {str(trained_for.get('sha256'))[:12]})"
    if is_default_file(given):
        raise InputError(f"{field} {weights!r}: the keypoint detector of {theirs}, not ENVISAT's ({DEFAULT_TARGET}): "
                         "give their target file (`target`; in Python the *_target calls, e.g. run_detect_target)")
    t = load_target(given)
    if t.sha256 != trained_for.get("sha256"):
        same = " (the same name: the file's bytes, or a file it names, changed since training; any edit, a comment "\
            "too, makes another target)" if t.name == trained_for.get("name") else ""
        raise InputError(f"{field} {weights!r}: the keypoint detector of {theirs}, not of target {t.name!r} "
                         f"({given}, sha256 {t.sha256[:12]}){same}: give the weights trained on this file")
