"""`envisat montecarlo --target`: another target's campaign (its truth from its inertia, the filter and the PCRLB
over its K keypoints), ENVISAT's campaign unchanged by naming its file, a bad file refused in one line.

Independent references: the PCRLB is recomputed here from the truth file with a measurement model written in the
test (rho + R^T v, R from the MRP's Euler axis and angle), not with the campaign's model."""

import json

import numpy as np

from envisat_pose.analysis.pcrlb import block_bounds, pcrlb_along_truth
from envisat_pose.app.cli import main
from envisat_pose.contracts import TruthTrajectory
from envisat_pose.filtering.dynamics import propagate
from envisat_pose.filtering.estimator import chaser_states
from envisat_pose.pipelines.campaigns.campaign_config import MonteCarloConfig
from envisat_pose.pipelines.tracking.onboard import onboard_physics
from envisat_pose.target import load_target

BASE = ["montecarlo", "--scenario", "default", "--runs", "30", "--duration-s", "300", "--settle-s", "150",
        "--measurements", "markers3d", "--seed", "5", "--quiet"]


def _markers(x, keypoints_T_m):
    """rho + Gamma^T v: Gamma (T from C, a passive rotation) of the MRP p is the turn by 4 atan|p| about p / |p|,
    I - sin(angle) [a x] + (1 - cos(angle)) [a x]^2."""
    p = x[..., 6:9]
    n = np.linalg.norm(p, axis=-1, keepdims=True)
    axis = p / np.where(n > 0, n, 1.0)
    angle = 4.0 * np.arctan(n)[..., None]
    K = np.zeros(p.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -axis[..., 2], axis[..., 1], -axis[..., 0]
    K = K - np.swapaxes(K, -1, -2)
    R_T_from_C = np.eye(3) - np.sin(angle) * K + (1 - np.cos(angle)) * K @ K
    return x[..., None, 0:3] + np.einsum("...ji,kj->...ki", R_T_from_C, keypoints_T_m)


def test_an_upper_stage_campaign_is_bounded_by_its_own_pcrlb(tmp_path):
    """30 runs of the upper stage (12 keypoints): every output, no divergence, RMSE over the campaign's PCRLB within
    [0.7, 1.4] per block (30 runs: a sampling spread of about +-13 % at 1 sigma), and the campaign's bound equal
    (1e-6 relative) to one recomputed here with the test's own measurement model and the file's inertia."""
    out = tmp_path / "us"
    # all 12 keypoints (the default scenario keeps the paper's max_markers = 8: the first 8 visible)
    assert main(BASE + ["--target", "models/upper_stage.xml", "--max-markers", "12", "--out", str(out)]) == 0
    s = json.loads((out / "summary.json").read_text())
    assert s["n_diverged"] == 0
    assert all(0.7 <= v <= 1.4 for v in s["rmse_over_pcrlb"].values()), s["rmse_over_pcrlb"]
    truth = TruthTrajectory.load(str(out / "truth.npz"))
    target = load_target("models/upper_stage.xml")
    assert truth.corners_C_m.shape[1] == target.num_keypoints == 12
    with np.load(out / "campaign.npz") as z:
        bound = z["pcrlb_block"]
    chaser = chaser_states(truth.chaser_r_m, truth.chaser_rdot_m_s, truth.chaser_theta_rad,
                           truth.chaser_thetadot_rad_s)
    J = target.inertia_T_kg_m2
    mu, gg = onboard_physics(truth, str(out / "truth.npz"))  # the truth's own mu and gravity-gradient switch

    def fx(X):
        return propagate(X, chaser[:-1, None, :], 1.0, J, mu, gravity_gradient=gg)

    def hx(X):
        return _markers(X, target.keypoints_T_m)

    P0 = MonteCarloConfig.from_scenario("default").filter.P0  # the scenario's [filter] p0_sigma, as the campaign's
    B = pcrlb_along_truth(fx, hx, truth.x, truth.visible, 0.02**2 * np.eye(3), P0, np.zeros((12, 12)))
    np.testing.assert_allclose(bound, block_bounds(B, truth.x), rtol=1e-6)


def test_naming_envisats_file_changes_nothing_and_a_bad_file_is_refused(tmp_path, capsys):
    short = ["montecarlo", "--scenario", "default", "--runs", "4", "--duration-s", "60", "--settle-s", "30",
             "--seed", "2", "--quiet"]
    assert main(short + ["--out", str(tmp_path / "plain")]) == 0
    assert main(short + ["--target", "models/envisat.xml", "--out", str(tmp_path / "named")]) == 0
    for name in ("campaign.npz", "truth.npz"):
        with np.load(tmp_path / "plain" / name) as a, np.load(tmp_path / "named" / name) as b:
            for key in a.files:
                if a[key].dtype.kind not in "US":
                    np.testing.assert_array_equal(a[key], b[key], err_msg=f"{name}:{key}")
    bad = tmp_path / "bad.xml"
    bad.write_text("<mujoco><worldbody/></mujoco>")
    capsys.readouterr()
    assert main(short + ["--target", str(bad), "--out", str(tmp_path / "bad")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "target" in err and "body named 'target'" in err, err
    assert not (tmp_path / "bad").exists()
