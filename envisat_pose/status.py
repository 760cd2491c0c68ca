"""The tracker's status per frame: its names, their codes and what each one claims (the one home of the concept).

Codes are what the per-frame arrays hold (`det.npz` / `est.npz` `status`, the closed loop's rows, the recording's
`status` series); the names and their meanings travel with every output (`legend()`), so a file read without this
package still says what 0, 1, 2, 3 mean. Codes never change meaning: a new status takes the next code.

- acquiring (0): no estimate yet; the tracker is collecting frames for its cold start. No state is claimed.
- tracking (1): the filter runs and its own evidence backs it this frame: corners were used, the innovations are
  consistent with its covariance and the state is physical (pipelines/integrity.py).
- lost (2): the evidence contradicted the state this frame; the bank is dropped and acquisition starts again.
- coasting (3): the filter predicts without a measurement this frame (no image, no corner found or every corner
  rejected); the state is a prediction, its covariance grows, and after a limit the track is declared lost.
"""

from __future__ import annotations

STATUSES = ("acquiring", "tracking", "lost", "coasting")
ACQUIRING, TRACKING, LOST, COASTING = range(len(STATUSES))

MEANINGS = {
    "acquiring": "no estimate: collecting frames for the cold start (no state claimed)",
    "tracking": "filter running and backed by this frame's corners: innovations consistent, state physical",
    "lost": "the evidence contradicted the state this frame: estimate dropped, acquisition restarts",
    "coasting": "filter predicting without a usable measurement this frame: a prediction, not a fix",
}

# the statuses whose rows hold a filter estimate (mean and covariance of a running filter)
HAS_ESTIMATE = (TRACKING, COASTING)


def status_code(name: str) -> int:
    """The code of a status name; a ValueError naming the valid ones otherwise."""
    try:
        return STATUSES.index(name)
    except ValueError:
        raise ValueError(f"status {name!r} is not one of {', '.join(STATUSES)}") from None


def status_name(code: int) -> str:
    """The name of a status code; a ValueError otherwise."""
    if not 0 <= int(code) < len(STATUSES):
        raise ValueError(f"status code {code} is not one of 0..{len(STATUSES) - 1}")
    return STATUSES[int(code)]


def legend() -> dict[str, dict[str, str]]:
    """{code as text: {"name", "meaning"}}: stored beside every status array (JSON) so a file explains itself."""
    return {str(i): {"name": s, "meaning": MEANINGS[s]} for i, s in enumerate(STATUSES)}


def legend_json() -> str:
    """legend() as the JSON text the outputs store (det.npz / est.npz `status_legend`, summary.json, recordings)."""
    import json

    return json.dumps(legend(), sort_keys=True)


def has_estimate(status):
    """Per row (any shape of codes): the row holds a filter estimate (tracking or coasting)."""
    import numpy as np

    return np.isin(np.asarray(status), HAS_ESTIMATE)
