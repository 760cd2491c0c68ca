"""Reading a target file into the checked fields of its `Target` (envisat_pose/target.py builds the Target from them
and caches it per file: load_target).

MuJoCo reads and compiles the file (target_file.read_spec: its child bodies fused, its joints latched); the body
`target` gives the mass and inertia about the CoM at its origin, its keypoint sites `kp_<name>` (or `corner_<name>`),
its geoms (TargetGeom) and its surface (target_mesh.body_mesh). Each check refuses the file with a ConfigError
naming the field, the value as given and what was expected.
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass

import numpy as np

from envisat_pose.attitude import quat_to_rotmat
from envisat_pose.config import ConfigError
from envisat_pose.config_errors import TargetFileWarning
from envisat_pose.target_assets import target_sha256
from envisat_pose.target_file import (
    check_inertia,
    drawn_alpha,
    inertial_used,
    keypoint_sites,
    misprefixed_keypoints,
    passed_over_sites,
    read_spec,
)
from envisat_pose.target_masses import com_hint
from envisat_pose.target_mesh import body_mesh
from envisat_pose.target_shape import triangle_distances

KEYPOINT_PREFIX = "kp_"
SCENE_KEYPOINT_PREFIX = "corner_"  # the keypoint sites of a file with no kp_ sites (models/envisat.xml)
MIN_KEYPOINTS = 4
KEYPOINT_MAX_SURFACE_DISTANCE_M = 0.05  # a keypoint farther than this from the target's surface is refused
RENDERED_GROUPS = (0, 1, 2)  # geom groups the factory always draws (MuJoCo's default visual groups)
COM_TOLERANCE = 1e-6  # the centre of mass's distance from the body's origin allowed, a share of MuJoCo's extent


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


def read_target_fields(path: str, field: str, given: str, named: str) -> dict:
    """The fields of the Target of the MJCF file at `path` (absolute, resolved), checked: {name, path, sha256,
    keypoint_names, keypoint_sites, keypoints_T_m, mass_kg, inertia_T_kg_m2, reach_m, geoms, surface, own_scene,
    latched_joints} (class Target). field, given: the words of its errors (ConfigError: load_target's checks);
    named: of its warning that the file's joints were latched."""
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
        _fail(field, given, f"at least {MIN_KEYPOINTS} keypoint sites named '{KEYPOINT_PREFIX}<name>' on body "
                            f"'target' (found {len(names)}{misprefixed_keypoints(model, body, KEYPOINT_PREFIX)})")
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
    passed = passed_over_sites(model, body, (KEYPOINT_PREFIX, SCENE_KEYPOINT_PREFIX), sites)
    if passed:  # said once per file (the load is cached), as the latched joints
        warnings.warn(f"{named}: site(s) {', '.join(map(repr, passed))} are not keypoints: a file with "
                      f"'{KEYPOINT_PREFIX}<name>' sites takes those alone ('{SCENE_KEYPOINT_PREFIX}<name>' sites only "
                      f"where it has none); name them '{KEYPOINT_PREFIX}<name>' to measure them", TargetFileWarning,
                      stacklevel=3)  # load_target's caller
    if latched:  # said once per file (the load is cached): the shape is the file's reference pose
        warnings.warn(f"{named}: {len(latched)} joint(s) latched at the file's reference pose, the target "
                      f"one rigid body ({', '.join(latched)})", TargetFileWarning, stacklevel=3)  # load_target's caller
    return dict(
        name=_model_name(spec, path),
        path=path, sha256=sha256, keypoint_names=names, keypoint_sites=sites, keypoints_T_m=X,
        mass_kg=float(model.body_mass[body]), inertia_T_kg_m2=inertia, reach_m=reach, geoms=geoms,
        surface=surface, own_scene=own_scene, latched_joints=latched)
