"""`envisat report`'s wall-time cell named one worker in the plural ("(1 local workers)"): it reads
"1 local worker" for one and "N ... workers" for more, in the row campaign_rows builds."""

from envisat_pose.pipelines.campaigns.report import campaign_rows
from envisat_pose.state import BLOCKS


def rows(workers) -> dict:
    s = {"scenario": "default", "runs": 4, "steps": 21, "duration_s": 20.0, "seed": 0, "settle_s": 10.0,
         "measurement": {"kind": "markers3d", "sigma_m": 0.02, "rate_hz": 1.0, "max_markers": None},
         "rmse": {b: 1e-3 for b in BLOCKS}, "inside_3sigma_share": {b: 1.0 for b in BLOCKS},
         "nees_mean": 12.0, "nees_bounds": [10.0, 14.0], "n_diverged": 0, "n_runs": 4}
    t = {"block_wall_s_sum": 2.5, "wall_s_this_invocation": 3.0, "workers": workers, "backend": "local"}
    return dict(campaign_rows({"dir": "c", "summary": s, "timing": t, "config": ""}))


def test_one_worker_is_singular_and_more_are_plural():
    assert rows(1)["wall time"] == "2.5 s in blocks, 3 s last invocation (1 local worker)"
    assert rows(4)["wall time"].endswith("(4 local workers)")


def test_no_timing_reads_n_a():
    no_timing = campaign_rows({"dir": "c", "summary": {"rmse": {}, "inside_3sigma_share": {}}, "timing": {},
                               "config": ""})
    assert dict(no_timing)["wall time"] == "n/a (no timing.json)"
