"""`envisat evaluate`'s table: a method without a figure (the classical peers have no visibility, no covariance)
shows '-' in its columns' width, so every row lines up under the header (issue 41)."""

from envisat_pose.pipelines.detector.evaluate import groups_table


def row(full: bool) -> dict:
    some = 0.5 if full else None
    return {"frames": 48, "errors": {"all": {"median_px": 0.4, "p95_px": 2.1}}, "pck_2px": 0.8, "pck_5px": 0.9,
            "swap_rate_strict": 0.0, "ambiguous_share": some, "visibility": {"precision": some, "recall": some},
            "calibration": {"mean_nees": 2.0 if full else None}, "pose": {}, "bias": {"scale_mean": None}}


def test_empty_cells_keep_the_columns():
    lines = groups_table({"clean": {"detector": row(True), "harris": row(False)}}).splitlines()
    head, full, empty = lines[0], lines[2], lines[3]
    assert len(full) == len(empty) == len(head)
    # each '-' stands where its column's values end (right-aligned), not one column to the left
    dashes = [i for i, c in enumerate(empty) if c == "-"]
    assert len(dashes) == 8  # ambig, vis P, vis R, NEES, t m, rot deg, scale, radial
    assert all(full[i] != " " and (i + 1 == len(full) or full[i + 1] == " ") for i in dashes)
