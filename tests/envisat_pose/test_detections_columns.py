"""det.npz's every column reads back through the contract: key and the half-turn alternative kept (issue 41), a
file without them still a Detections, and a wrong dtype in one of them refused by name."""

import json

import numpy as np
import pytest

from envisat_pose.contracts import ContractError, Detections
from envisat_pose.io import save_npz


def det_arrays(F=3):
    rng = np.random.default_rng(4)
    visible = rng.random((F, 8)) < 0.7
    corners = np.where(visible[..., None], rng.uniform(0, 512, (F, 8, 2)), np.nan)
    return {"t_s": np.arange(F, dtype=float), "corners_px": corners,
            "cov_px": np.broadcast_to(np.eye(2), (F, 8, 2, 2)).copy(), "confidence": visible * 0.9,
            "visible": visible, "config_json": json.dumps({"weights": "w"})}


def test_the_optional_columns_of_det_npz_are_loaded(tmp_path):
    a = det_arrays()
    extra = {"key": np.array(["000000000", "000000001", "000000002"]),
             "alt_corners_px": np.full((3, 8, 2), np.nan), "alt_probability": np.array([0.0, 0.2, 0.5]),
             "ambiguous": np.array([False, False, True])}
    save_npz(str(tmp_path / "det.npz"), {**a, **extra})
    d = Detections.load(str(tmp_path / "det.npz"))
    assert d.key.tolist() == extra["key"].tolist()
    assert np.array_equal(d.ambiguous, extra["ambiguous"]) and np.allclose(d.alt_probability, [0, 0.2, 0.5])
    assert d.alt_corners_px.shape == (3, 8, 2)
    d.save(str(tmp_path / "again.npz"))
    assert Detections.load(str(tmp_path / "again.npz")).key.tolist() == extra["key"].tolist()


def test_a_file_without_them_still_loads_and_a_bad_one_is_named(tmp_path):
    save_npz(str(tmp_path / "plain.npz"), det_arrays())
    d = Detections.load(str(tmp_path / "plain.npz"))
    assert d.key is None and d.ambiguous is None
    save_npz(str(tmp_path / "bad.npz"), {**det_arrays(), "key": np.arange(3)})
    with pytest.raises(ContractError, match="'key' has dtype"):
        Detections.load(str(tmp_path / "bad.npz"))
    save_npz(str(tmp_path / "short.npz"), {**det_arrays(), "ambiguous": np.zeros(2, bool)})
    with pytest.raises(ContractError, match="has shape .*F = 2"):
        Detections.load(str(tmp_path / "short.npz"))
