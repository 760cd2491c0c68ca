"""A recording read back as plain Python (tests, checks): Rerun's own reader, every chunk."""

from __future__ import annotations

import warnings

import numpy as np
import rerun as rr


def read_recording(path: str) -> tuple[dict, dict]:
    """Read a .rrd back as plain Python: (static, temporal), where static is {entity: {column: value}} and
    temporal is {entity: {column: [rows sorted by the frame timeline]}} (columns as Rerun names them)."""
    static: dict = {}
    temporal: dict = {}
    with warnings.catch_warnings():  # older TrackRecorder files have no footer (read whole, as here: nothing lost)
        warnings.filterwarnings("ignore", message=".*no footer/manifest.*")
        reader = rr.chunk.RrdReader(str(path))
    for chunk in reader.stream().collect().stream():
        d = chunk.to_record_batch().to_pydict()
        d.pop("rerun.controls.RowId", None)
        if "frame" in d:
            t = temporal.setdefault(chunk.entity_path, {})
            rows = len(t["frame"]) if "frame" in t else 0
            n = len(d["frame"])
            for k in set(t) | set(d):  # chunks of one entity may carry different columns (a Clear, say)
                t.setdefault(k, [None] * rows).extend(d.get(k, [None] * n))
        else:
            static.setdefault(chunk.entity_path, {}).update({k: v[-1] for k, v in d.items()})
    for t in temporal.values():
        order = np.argsort(t["frame"], kind="stable")
        for k in t:
            t[k] = [t[k][i] for i in order]
    return static, temporal
