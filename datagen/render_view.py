"""What the renderer takes and returns: one view (View: the target's pose, the sun and the Earth in the chaser
frame C, the appearance), the GL passes read back (RenderPasses) and the rendered images and labels (RenderOutput), with
the mask's values (MASK_VALUES, or another target's geom order: target_mask_values)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from envisat_pose.datagen.appearance import Appearance, takes_class_appearance
from envisat_pose.datagen.target_scene import target_scene
from envisat_pose.target import Target

# Mask values: 0 background (and the Earth), 1-6 the faces in geometry.FACE_NAMES order, 7 the solar array
# (its boom included: the contract has one value per face and one for the array).
MASK_VALUES = {"face_px": 1, "face_mx": 2, "face_py": 3, "face_my": 4, "face_pz": 5, "face_mz": 6, "array": 7, "boom": 7,
               "asar": 8, "asar_strut_fwd": 8, "asar_strut_aft": 8, "instr_meris": 8, "instr_aatsr": 8,
               "instr_doris": 8}
# The clutter's (ASAR antenna, instrument boxes: render.APPENDAGE_GEOM_GROUP) mask value.
APPENDAGE_MASK_VALUE = 8


@dataclass(frozen=True)
class View:
    """What one image shows, everything in the chaser frame C.

    rho_C_m: (3,) target CoM relative to the chaser, m. R_C_from_T: (3, 3) target attitude (Gamma^T).
    sun_dir_C: (3,) unit vector toward the sun; None means eclipse (no sunlight).
    earth_dir_C: (3,) unit vector toward the Earth's centre (nadir); None means no Earth (no backdrop, no
    Earth-shine). earth_backdrop: draw the Earth (textured, lit by the sun) when earth_dir_C is given.
    earth_distance_m: distance of the Earth's centre from the chaser, m (its disc's angular radius is
    asin(R / earth_distance_m)). earth_quat_C: (4,) attitude of the Earth's body frame (z to the north pole,
    x to longitude 0) in C, w x y z; None: the identity. earth_texture: which of the renderer's Earth textures.
    appearance: per-geom materials and light intensities (appearance.Appearance); None keeps the MJCF's materials,
    the sun at its MJCF intensity and no Earth-shine. appendages: draw the clutter (ASAR antenna, instruments).
    The Earth-shine light shines from earth_dir_C at the appearance's intensity.
    """

    rho_C_m: np.ndarray
    R_C_from_T: np.ndarray
    sun_dir_C: np.ndarray | None
    earth_dir_C: np.ndarray | None = None
    earth_distance_m: float = 7142.0e3
    appearance: Appearance | None = None
    appendages: bool = False
    earth_backdrop: bool = True
    earth_quat_C: np.ndarray | None = None
    earth_texture: int = 0


@dataclass
class RenderOutput:
    """One rendered view.

    gray_u8: (H, W) uint8 image. depth_m: (H, W) float32 metres along the boresight, 0 on background.
    mask_u8: (H, W) uint8, MASK_VALUES, or another target's geom order (depth_m and mask_u8 None when rendered
    without labels). corners_K_m: (K, 3) the target's keypoints (ENVISAT: corners A-H) in the camera frame K, m.
    R_K_from_T: (3, 3), t_K_from_T_m: (3,) the target pose in K (the label's R_cam_from_target, t_cam_from_target_m).
    fovy_deg: the camera's vertical field of view.
    """

    gray_u8: np.ndarray
    depth_m: np.ndarray | None
    mask_u8: np.ndarray | None
    corners_K_m: np.ndarray
    R_K_from_T: np.ndarray
    t_K_from_T_m: np.ndarray
    fovy_deg: float


@dataclass
class RenderPasses:
    """What the GL passes of one view read back, before any pixel work (SceneRenderer.decode makes the
    RenderOutput of it; touching no GL state, that may run on another thread).

    rgb_u8: (H, W, 3) the lit pass, rows bottom-up. box: (u0, v0, u1, v1) px of the segmentation and depth pass
    (None: rendered without labels). ids_rgb_u8: (h, w, 3) its segmentation colours and depth_raw: (h, w) float32
    its depth-buffer values, rows bottom-up. slot_value: (n,) uint8 the mask value of each segmentation colour
    (scene slot + 1). corners_K_m, R_K_from_T, t_K_from_T_m: as in RenderOutput.
    """

    rgb_u8: np.ndarray
    box: tuple[int, int, int, int] | None
    ids_rgb_u8: np.ndarray | None
    depth_raw: np.ndarray | None
    slot_value: np.ndarray | None
    corners_K_m: np.ndarray
    R_K_from_T: np.ndarray
    t_K_from_T_m: np.ndarray


def target_mask_values(target: Target) -> dict:
    """{geom name: mask value} of a target: MASK_VALUES for one that takes the class appearance
    (appearance.takes_class_appearance), 1..G in file order for any other (target_scene)."""
    return MASK_VALUES if takes_class_appearance(g.name for g in target.geoms) else target_scene(target).mask_values
