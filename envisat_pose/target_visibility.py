"""The fast form of a target's keypoint visibility: a table over view directions and ranges, looked up in O(1).

Built from a Target's exact ray casts (`Target.visible_from`) by `build_visibility_table`; `Target.visibility_table`
builds it once per target file and process (envisat_pose/target.py), and a filter's visibility check looks it up
(filtering/measurements.py, and filtering/fast.py's kernel with the same grid and formulas).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from envisat_pose.target_shape import fibonacci_directions

TABLE_DIRECTIONS = 2048  # view directions of the fast visibility table (about 4.5 deg apart)
TABLE_RANGES_REACHES = (3.0, 8.0, 30.0, 1000.0)  # ... each cast from these many reaches away (the last: parallel)
TABLE_NEIGHBOURS = 2  # a keypoint is called hidden only where this many nearest directions hide it too
SEEN_CHECK_DIRECTIONS = 64  # a keypoint hidden from each of these (at 3 reaches) is warned of when its file loads
TABLE_CELLS_POLAR = 256  # polar rows of the grid that finds a view's direction (azimuth columns: twice as many)


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
    the cell's centre (cells 0.7 deg across, a sixth of the directions' spacing; the first of equals). A row's
    centres share their z, so a direction nearer than a row's found ones lies within their largest distance of it
    in z: each row is searched in a band of z that holds that distance (widened until it does), not all of dirs."""
    polar = (np.arange(rows) + 0.5) * np.pi / rows
    azimuth = (np.arange(2 * rows) + 0.5) * np.pi / rows - np.pi
    by_z = np.argsort(dirs[:, 2], kind="stable")
    z_sorted = dirs[by_z, 2]
    cells = np.empty((rows, 2 * rows), np.int16)
    for i, p in enumerate(polar):
        centres = np.stack([np.sin(p) * np.cos(azimuth), np.sin(p) * np.sin(azimuth), np.full(2 * rows, np.cos(p))],
                           axis=-1)
        half = 2.0 * np.sqrt(4.0 * np.pi / len(dirs))  # twice the directions' spacing
        while True:
            lo, hi = np.searchsorted(z_sorted, np.cos(p) - half), np.searchsorted(z_sorted, np.cos(p) + half, "right")
            band = np.sort(by_z[lo:hi])  # in index order: argmax keeps the first of equals, as over all of dirs
            dots = centres @ dirs[band].T
            farthest = np.sqrt(max(0.0, 2.0 - 2.0 * dots.max(axis=1).min())) if len(band) else np.inf
            if farthest + 1e-9 < half or (lo == 0 and hi == len(dirs)):
                break
            half *= 2.0
        cells[i] = band[np.argmax(dots, axis=1)]
    return cells


def build_visibility_table(target, appendages: bool) -> VisibilityTable:
    """The table of `target` (a Target: its reach_m and exact visible_from), the geoms of the `appendages` switch
    drawn or not: exact visibility from TABLE_DIRECTIONS directions at TABLE_RANGES_REACHES x reach, each widened to
    its TABLE_NEIGHBOURS nearest directions. Its 8,192 positions cast in one batch (visible_from): 0.2-0.5 s for
    each shipped target and either `appendages` (a 2-core machine shared with other jobs, load 2.4-3.3; cast one
    position at a time as before, 4-15 s; bench/visibility_cost.py --table-only)."""
    dirs = fibonacci_directions(TABLE_DIRECTIONS)
    ranges_m = np.array(TABLE_RANGES_REACHES) * target.reach_m
    exact = target.visible_from(dirs[None] * ranges_m[:, None, None], appendages)  # (B, N, K)
    nearest = np.argsort(-(dirs @ dirs.T), axis=1)[:, :TABLE_NEIGHBOURS + 1]  # each direction first
    return VisibilityTable(dirs, ranges_m, np.ascontiguousarray(exact[:, nearest].any(axis=2)), direction_cells(dirs))


def never_seen(target) -> list[str]:
    """The keypoint sites of `target` (a Target) that no view sees: hidden from each of SEEN_CHECK_DIRECTIONS
    directions 3 reaches away (exact visible_from; a site inside a solid, within the 5 cm of its surface a file
    is allowed). Every keypoint of the shipped targets is seen from 35 or more of them; ~1 ms."""
    dirs = fibonacci_directions(SEEN_CHECK_DIRECTIONS) * (TABLE_RANGES_REACHES[0] * target.reach_m)
    seen = target.visible_from(dirs).any(axis=0)
    return [site for site, s in zip(target.keypoint_sites, seen) if not s]
