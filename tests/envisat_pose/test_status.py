"""The tracker's status names and codes: one home, stable codes, a legend that covers every code."""

import json

import pytest

from envisat_pose import status


def test_codes_keep_their_meaning():
    # files written before "coasting" existed hold 0, 1, 2: those codes must keep their names
    assert status.STATUSES[:3] == ("acquiring", "tracking", "lost")
    assert (status.ACQUIRING, status.TRACKING, status.LOST, status.COASTING) == (0, 1, 2, 3)


def test_legend_names_every_code_and_round_trips_through_json():
    leg = json.loads(json.dumps(status.legend()))
    assert [leg[str(i)]["name"] for i in range(len(status.STATUSES))] == list(status.STATUSES)
    assert all(leg[k]["meaning"] for k in leg)


def test_bad_names_and_codes_are_refused():
    assert status.status_code("coasting") == 3 and status.status_name(1) == "tracking"
    with pytest.raises(ValueError, match="not one of"):
        status.status_code("converged")
    with pytest.raises(ValueError, match="not one of"):
        status.status_name(4)
