"""`envisat estimate` with a filter rate whose period is as long as the truth, or longer."""

import numpy as np

from envisat_pose.app.cli import main


def test_a_period_longer_than_the_truth_is_refused_in_one_line(tmp_path, capsys):
    """0.01 Hz over a 60 s truth at 1 s: its 100 s period left the filter its first step alone (t = 0 s), which
    ran and said "after t = 0 s" for its summary. Refused before any folder is made, naming the flag, the period and
    the truth's span; 1/60 Hz, a period as long as the truth, still filters its two ends, 0 and 60 s."""
    from envisat_pose.datagen.scenario import scenario_config
    from envisat_pose.datagen.truth import simulate_truth

    truth = tmp_path / "run.npz"
    simulate_truth(scenario_config("default", duration_s=60.0, seed=2)).save(str(truth))
    out = tmp_path / "new" / "est.npz"
    assert main(["estimate", "--truth", str(truth), "--rate-hz", "0.01", "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert "--rate-hz 0.01" in err and "100 s" in err and "60 s" in err, err
    assert not (tmp_path / "new").exists()

    assert main(["estimate", "--truth", str(truth), "--rate-hz", str(1.0 / 60.0), "--out", str(out), "--quiet"]) == 0
    with np.load(out) as z:
        np.testing.assert_allclose(z["t_s"], [0.0, 60.0], rtol=0, atol=1e-9)
