"""The target: one spacecraft, read once from its MJCF file into one `Target` that every layer takes.

A target file's worldbody holds one body named `target` with its <inertial> (mass, inertia about the centre of
mass at the body's origin; without one, what MuJoCo computes from the geoms, their CoM at the origin), its geoms
and materials, and its keypoints as the body's sites `kp_<name>` in file order (a file with none takes its
`corner_<name>` sites: models/envisat.xml's corners A-H). The body frame of the
file is the frame T of the labels, the truth and the filter. The file is read by MuJoCo itself (MjSpec), so its own
<compiler> (angle unit, eulerseq, meshdir, texturedir), defaults and assets give the shape MuJoCo gives it alone;
child bodies are fused into it as MuJoCo fuses static bodies, joints latched (envisat_pose/target_file.py).

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

from envisat_pose.attitude import quat_to_rotmat
from envisat_pose.config import ConfigError, InputError
from envisat_pose.geometry import model_path, visible_corners
from envisat_pose.shard_reader import load_dataset_manifest
from envisat_pose.target_file import (
    check_inertia,
    drawn_alpha,
    inertial_used,
    keypoint_sites,
    misprefixed_keypoints,
    named_files,
    read_spec,
    target_sha256,
)
from envisat_pose.target_masses import com_hint
from envisat_pose.target_mesh import BodyMesh, TriangleMesh, body_mesh, feature_edges
from envisat_pose.target_rays import ray_hits_m
from envisat_pose.target_shape import (
    Symmetry,
    fibonacci_directions,
    mirror_perm,
    skeleton,
    symmetries,
    triangle_distances,
)

DEFAULT_TARGET = "models/envisat.xml"  # the default `target` of every config (the package's file)
KEYPOINT_PREFIX = "kp_"
SCENE_KEYPOINT_PREFIX = "corner_"  # the keypoint sites of a file with no kp_ sites (models/envisat.xml)
MIN_KEYPOINTS = 4
KEYPOINT_MAX_SURFACE_DISTANCE_M = 0.05  # a keypoint farther than this from the target's surface is refused
RENDERED_GROUPS = (0, 1, 2)  # geom groups the factory always draws (MuJoCo's default visual groups)
APPENDAGE_GROUP = 4  # geom group of the clutter the `appendages` switch draws (models/envisat.xml)
RAY_ABS_TOL_M = 1e-4  # a surface this much nearer than a keypoint (plus 1e-6 of its range) does not hide it
TABLE_DIRECTIONS = 2048  # view directions of the fast visibility table (about 4.5 deg apart)
COM_TOLERANCE = 1e-6  # the centre of mass's distance from the body's origin allowed, a share of MuJoCo's extent
TABLE_RANGES_REACHES = (3.0, 8.0, 30.0, 1000.0)  # ... each cast from these many reaches away (the last: parallel)
TABLE_NEIGHBOURS = 2  # a keypoint is called hidden only where this many nearest directions hide it too
TABLE_CELLS_POLAR = 256  # polar rows of the grid that finds a view's direction (azimuth columns: twice as many)


@dataclass(frozen=True)
class TargetGeom:
    """One geom of body `target`: name (its own, or target_geom_<i>), MuJoCo type name, group, material name
    ('' for none) and rgb (3,) of its material (or its own rgba); alpha: the alpha MuJoCo's renderer draws it with
    (drawn_alpha). shown: MuJoCo draws it (alpha above 0; an invisible geom is left out of the images and the
    visibility). opaque: alpha 1, the geoms that hide keypoints (Target.occluding)."""

    name: str
    type: str
    group: int
    material: str
    rgb: tuple[float, float, float]
    alpha: float = 1.0

    @property
    def shown(self) -> bool:
        return self.alpha > 0.0

    @property
    def opaque(self) -> bool:
        return self.alpha >= 1.0


@dataclass(frozen=True, eq=False)
class Target:
    """A checked target file, read once.

    name: the file's model name (<mujoco model=...>) or its stem. path: absolute. sha256: of the file's bytes and
    of the files it names (target_file.target_sha256).
    keypoint_names (K,), keypoint_sites (K,) their MJCF site names; keypoints_T_m (K, 3) in T, m. mass_kg;
    inertia_T_kg_m2 (3, 3) about the CoM in T. reach_m: the farthest point of its surface from the CoM. geoms:
    (G,) TargetGeom, file order. surface: the triangles of every geom in T (target_mesh.BodyMesh). own_scene: the
    file holds the factory's scene (target_file.SCENE_NAMES), so it is rendered as it is. latched_joints: the
    file's joints in the target's tree, latched at their reference pose (target_file.py: the target is one rigid
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
        """Exact visibility of each keypoint from the point c_T_m (3,) in T: the ray from it to the keypoint
        meets no opaque drawn geom of the target before it (occluding; MuJoCo's own ray-geom intersections, less
        RAY_ABS_TOL_M plus 1e-6 of the range). The one rule of the labels, the truth and the filters' table.
        (K,) bool."""
        c_T = np.asarray(c_T_m, float)
        hits = ray_hits_m(self.path, self.sha256, c_T, self.keypoints_T_m, self.occluding(appendages))
        rng = np.linalg.norm(self.keypoints_T_m - c_T, axis=1)
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
        up by the nearest range and direction (built once per target and process, ~6 s on one core)."""
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
        return np.array([self.visible_from(p) for p in c], bool).reshape(len(c), self.num_keypoints)


# ---------------------------------------------------------------- the fast form: a table over view directions


@dataclass(frozen=True, eq=False)
class VisibilityTable:
    """Keypoint visibility by view direction and range, in the sense a filter's visibility check needs: a keypoint
    the table calls hidden is hidden (the check drops a measured keypoint it calls hidden as a mislabel), one it
    calls visible may be hidden near a silhouette. dirs_T: (N, 3) unit directions from the CoM toward the camera,
    in T (a Fibonacci sphere); ranges_m: (B,) the ranges cast from; visible: (B, N, K) bool, exact ray casts from
    each range along the direction or one of its TABLE_NEIGHBOURS nearest. Measured against the exact casts from
    400 random positions per span (seed 3, range log-uniform in 2-8 and 8-150 reaches): visible keypoints called
    hidden 0.1-0.4 % (CubeSat, upper stage; the single-range, single-direction table of before: 1-11 %, most at
    long range), hidden ones called visible 9-11 % (tests/envisat_pose/test_target.py holds them under 1 % and
    15 %)."""

    dirs_T: np.ndarray
    ranges_m: np.ndarray
    visible: np.ndarray
    cell_dir: np.ndarray

    def lookup(self, c_T_m: np.ndarray) -> np.ndarray:
        """Visibility from camera positions c_T_m (..., 3) in T: the row of the direction at the camera's cell
        (cell_dir, polar_azimuth_cell) at the nearest range (in log). (..., K) bool; a position that is not finite
        (a broken filter run's) sees every keypoint: nothing known hides one."""
        c = np.asarray(c_T_m, float)
        finite = np.isfinite(c).all(axis=-1)
        c = np.where(finite[..., None], c, 1.0)
        r = np.linalg.norm(c, axis=-1)
        b = np.argmin(np.abs(np.log(np.maximum(r, 1e-12))[..., None] - np.log(self.ranges_m)), axis=-1)
        i, j = polar_azimuth_cell(c, r, self.cell_dir.shape[0])
        return self.visible[b, self.cell_dir[i, j]] | ~finite[..., None]


def polar_azimuth_cell(c: np.ndarray, r: np.ndarray, rows: int) -> tuple[np.ndarray, np.ndarray]:
    """(row, column) of the points c (..., 3) of norm r (...,) in a grid of `rows` bands of polar angle (from +z)
    by 2 x rows sectors of azimuth, each 180 / rows deg: a view's direction found in O(1) (filtering/fast.py's
    kernel computes the same)."""
    polar = np.arccos(np.clip(c[..., 2] / np.maximum(r, 1e-12), -1.0, 1.0))
    i = np.minimum((polar * (rows / np.pi)).astype(np.intp), rows - 1)
    j = np.minimum(((np.arctan2(c[..., 1], c[..., 0]) + np.pi) * (rows / np.pi)).astype(np.intp), 2 * rows - 1)
    return i, j


def direction_cells(dirs: np.ndarray, rows: int = TABLE_CELLS_POLAR) -> np.ndarray:
    """(rows, 2 rows) int16: for each cell of polar_azimuth_cell's grid, the direction of dirs (N, 3) nearest to
    the cell's centre (cells 0.7 deg across, a sixth of the directions' spacing)."""
    polar = (np.arange(rows) + 0.5) * np.pi / rows
    azimuth = (np.arange(2 * rows) + 0.5) * np.pi / rows - np.pi
    p, a = np.meshgrid(polar, azimuth, indexing="ij")
    centres = np.stack([np.sin(p) * np.cos(a), np.sin(p) * np.sin(a), np.cos(p)], axis=-1).reshape(-1, 3)
    nearest = [np.argmax(chunk @ dirs.T, axis=1) for chunk in np.array_split(centres, 64)]
    return np.concatenate(nearest).astype(np.int16).reshape(rows, 2 * rows)


@functools.lru_cache(maxsize=16)
def _table(path: str, sha256: str, appendages: bool) -> VisibilityTable:
    target = load_target(path)
    dirs = fibonacci_directions(TABLE_DIRECTIONS)
    ranges_m = np.array(TABLE_RANGES_REACHES) * target.reach_m
    exact = np.array([[target.visible_from(d * r, appendages) for d in dirs] for r in ranges_m], bool)
    nearest = np.argsort(-(dirs @ dirs.T), axis=1)[:, :TABLE_NEIGHBOURS + 1]  # each direction first
    return VisibilityTable(dirs, ranges_m, np.ascontiguousarray(exact[:, nearest].any(axis=2)), direction_cells(dirs))


# ---------------------------------------------------------------- reading the file


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


def _fail(field: str, given: str, expected: str):
    raise ConfigError(field, given, expected)


def _geoms(model, body: int) -> tuple[TargetGeom, ...]:
    import mujoco

    out = []
    for i, g in enumerate(np.flatnonzero(model.geom_bodyid == body)):
        mat = int(model.geom_matid[g])
        rgb = model.mat_rgba[mat][:3] if mat >= 0 else model.geom_rgba[g][:3]
        out.append(TargetGeom(model.geom(g).name or f"target_geom_{i}",
                              mujoco.mjtGeom(int(model.geom_type[g])).name.removeprefix("mjGEOM_").lower(),
                              int(model.geom_group[g]), model.material(mat).name if mat >= 0 else "",
                              tuple(float(v) for v in rgb), drawn_alpha(model, g)))
    return tuple(out)


def _model_name(spec, path: str) -> str:
    """The file's <mujoco model=...>, or its file name's stem where it has none."""
    with open(path, encoding="utf-8", errors="replace") as fh:
        head = fh.read(4096)
    stated = "model=" in head.split("<mujoco", 1)[-1].split(">", 1)[0] if "<mujoco" in head else False
    return spec.modelname if stated and spec.modelname else os.path.splitext(os.path.basename(path))[0]


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
    field, given = naming.field, naming.given
    sha256 = target_sha256(path)
    spec, own_scene, fused, latched = read_spec(path, field, given)
    try:
        model = spec.compile()
    except ValueError as err:
        _fail(field, given, f"an MJCF file MuJoCo compiles (it says: {' '.join(str(err).split())})")
    body = model.body("target").id
    R = quat_to_rotmat(model.body_iquat[body])
    inertia = R @ np.diag(model.body_inertia[body]) @ R.T
    stated = inertial_used(spec, spec.body("target")) and not fused  # else MuJoCo's sums
    whose = ("the masses of the body and its child bodies" if fused else
             "its geoms' masses (the compiler's inertiafromgeom='true' sets its <inertial> aside)"
             if spec.body("target").explicitinertial else
             "its geoms' masses (it has no <inertial>: state one, or give its geoms their mass or density)")
    if not stated or spec.compiler.balanceinertia:
        problem = check_inertia(float(model.body_mass[body]), inertia)
        if problem is not None:
            _fail(field, given, f"body 'target' with {problem}, as MuJoCo computes them from {whose}")
    com = model.body_ipos[body]  # at the origin to a millionth of the model's size (rounded positions, a feather)
    if np.linalg.norm(com) > COM_TOLERANCE * max(float(model.stat.extent), 1e-3):
        where = com_hint(path, fused, stated, whose, com)
        _fail(field, given, f"the centre of mass at the body's origin ({where}): T's origin is the CoM")
    names, sites, X = keypoint_sites(model, body, (KEYPOINT_PREFIX, SCENE_KEYPOINT_PREFIX))
    if len(names) < MIN_KEYPOINTS:
        _fail(field, given, f"at least {MIN_KEYPOINTS} keypoint sites named '{KEYPOINT_PREFIX}<name>' on body 'target' (found "
                            f"{len(names)}{misprefixed_keypoints(model, body, KEYPOINT_PREFIX)})")
    if len(set(names)) != len(names) or "" in names:
        _fail(field, given, f"keypoint sites with distinct, non-empty names after the prefix (got {list(names)})")
    geoms = _geoms(model, body)
    surface = body_mesh(model, body)
    if len(surface.mesh.faces) == 0:
        _fail(field, given, "geoms with a surface on body 'target' (boxes, cylinders, spheres, meshes...)")
    groups = ", ".join(str(g) for g in RENDERED_GROUPS)
    drawn = surface.select(np.array([g.group in RENDERED_GROUPS and g.shown for g in geoms], bool))
    if len(drawn.faces) == 0:  # nothing in the images, every keypoint labelled visible
        _fail(field, given, f"geoms the factory draws on body 'target' (groups {groups}, MuJoCo's visible ones, "
                            f"alpha above 0; its geoms are in groups {sorted({g.group for g in geoms})}, "
                            f"{sum(not g.shown for g in geoms)} of alpha 0)")
    dist = triangle_distances(X, drawn.vertices_T_m[drawn.faces]).min(axis=1)
    k = int(np.argmax(dist))
    if dist[k] > KEYPOINT_MAX_SURFACE_DISTANCE_M:
        _fail(field, given, f"keypoints on the target: site {sites[k]!r} is {dist[k]:.3f} m from the nearest "
                            f"surface of the geoms the factory draws (inside a solid or off it; groups {groups}; at "
                            f"most {KEYPOINT_MAX_SURFACE_DISTANCE_M:g} m)")
    reach = float(np.linalg.norm(surface.mesh.vertices_T_m, axis=1).max())
    if latched:  # said once per file (the load is cached): the shape is the file's reference pose
        warnings.warn(f"{naming.named}: {len(latched)} joint(s) latched at the file's reference pose, the target "
                      f"one rigid body ({', '.join(latched)})", stacklevel=2)
    return Target(
        name=_model_name(spec, path),
        path=path, sha256=sha256, keypoint_names=names, keypoint_sites=sites, keypoints_T_m=X,
        mass_kg=float(model.body_mass[body]), inertia_T_kg_m2=inertia, reach_m=reach, geoms=geoms,
        surface=surface, own_scene=own_scene, latched_joints=latched)


def load_target(given: str = DEFAULT_TARGET, field: str = "target", named: str | None = None) -> Target:
    """Returns a Target: the checked target of a config's `target` value, read once (its keypoints in T, m, its
    mass and inertia, its surface, sha256: class Target). given: a path; DEFAULT_TARGET is the package's ENVISAT;
    named: how its warnings name the file where it comes from elsewhere than `field`, a truth file's record).
    ConfigError naming `field`, the value and what was expected: no such file, a file MuJoCo cannot read or
    compile, no body 'target' (its child bodies are read fused, its joints latched: target_file.py), a bad
    inertia (zero mass, not positive definite, the triangle inequality; stated by an <inertial>, or else MuJoCo's
    from the geoms and child bodies), the CoM off the body's origin, fewer than 4 keypoint sites, no geom the
    factory draws (RENDERED_GROUPS), a keypoint farther than KEYPOINT_MAX_SURFACE_DISTANCE_M from the drawn
    surface. Cached per file, size and modification time, its named files' too (target_file.named_files)."""
    path = resolve_target_path(given)
    if not os.path.isfile(path) or not path.endswith(".xml"):  # MuJoCo picks its reader by the name's ending
        _fail(field, given, "an MJCF file (no such file)" if not os.path.isfile(path) else "an MJCF file whose name "
              "ends in .xml (MuJoCo reads a model file by its ending, .xml alone as MJCF: copy or link it so)")
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


def envisat_only(verb: str) -> str:
    other = ("; another target's keypoint detector: --target FILE.xml" if verb in ("train", "detect") else
             "; another target's images and labels come from `envisat generate --target` (docs/usage.md)")
    return f"ENVISAT ({DEFAULT_TARGET}): `envisat {verb}` and the detector know ENVISAT's corners A-H only" + other


def require_envisat(given: str, field: str, verb: str) -> None:
    """ConfigError unless the `target` value `given` names ENVISAT: the detector and the verbs built on it (track,
    run, adapt, train, detect) know ENVISAT only."""
    if given != DEFAULT_TARGET and not load_target(given, field).is_default:
        raise ConfigError(field, given, envisat_only(verb))


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
        raise ConfigError(field, folder, envisat_only(verb) + f"; this dataset's target is {given!r}")


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
