"""The tracker's status per frame: its names, their codes and what each one claims (the one home of the concept).

Codes are what the per-frame arrays hold (`det.npz` / `est.npz` `status`, the closed loop's rows, the recording's
`status` series); the names and their meanings travel with every output (`legend()`), so a file read without this
package still says what 0, 1, 2, 3 mean. Codes never change meaning: a new status takes the next code.

- acquiring (0): no claim: the tracker is collecting frames for its cold start, or a started bank has not yet
  earned a claim (its half-turn still open, or not yet confirmed by its own innovations).
- tracking (1): one confirmed hypothesis whose evidence backs it this frame: corners were used, its windowed
  innovations are consistent with its covariance, its state is physical, and its 3-sigma is inside the claimed
  accuracy (pipelines/tracking/integrity.py).
- lost (2): the evidence contradicted the state this frame; the bank is dropped and acquisition starts again.
- coasting (3): a confirmed track predicting without a usable measurement this frame (no image, no corner found,
  every corner rejected) or with a covariance wider than the claim; a prediction, not a fix. Frames with an
  image and no corner used are limited (then lost); frames without an image coast until the covariance is too
  wide.
"""

from __future__ import annotations

STATUSES = ("acquiring", "tracking", "lost", "coasting")
ACQUIRING, TRACKING, LOST, COASTING = range(len(STATUSES))

MEANINGS = {
    "acquiring": "no claim: collecting frames for the cold start, or a started track not yet confirmed",
    "tracking": "one confirmed hypothesis backed by this frame's corners: innovations consistent, state physical, "
                "3-sigma inside the claimed accuracy",
    "lost": "the evidence contradicted the state this frame: estimate dropped, acquisition restarts",
    "coasting": "a confirmed track predicting without a usable measurement (or wider than the claim): "
                "a prediction, not a fix",
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
