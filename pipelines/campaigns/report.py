"""The HTML report over Monte Carlo campaigns (`envisat report`): one self-contained page.

Per campaign folder (written by `envisat montecarlo`): the scenario and its config, a table of RMSE per block
after the settle time, the share of run-steps inside the filter's 3-sigma, the mean NEES with its 95 % band,
the PCRLB and RMSE/PCRLB per block, diverged runs and wall time, and the campaign's figures embedded as
base64 PNG data URIs. Several folders sit side by side (one column each). A rate-sweep folder (sweep.json)
gets a table with a row per rate and its figure. No external link or resource. `write_report` is the job.
"""

from __future__ import annotations

import base64
import html
import json
import math
import os
import tomllib
import warnings

from envisat_pose.config import InputError, flatten, path_arg, paths_arg
from envisat_pose.io import atomic_write_text
from envisat_pose.out_dirs import check_out_file, make_out_file_dirs
from envisat_pose.out_lock import locks_output
from envisat_pose.pipelines.campaigns.campaign import CONFIG_NAME, MANIFEST_FORMAT, SWEEP_RATE_CONFIG
from envisat_pose.pipelines.campaigns.sweep import SWEEP_FIGURE
from envisat_pose.resumable import read_manifest
from envisat_pose.state import BLOCKS, unjudged_why
from envisat_pose.target import DEFAULT_TARGET

# display unit and scale per block (the summary's units are m, m/s, rad, rad/s)
DISPLAY = {"position": ("cm", 100.0), "velocity": ("mm/s", 1000.0), "attitude": ("deg", 180.0 / math.pi),
           "angular_velocity": ("deg/s", 180.0 / math.pi)}
FIGURE_CAPTIONS = {
    "envelopes.png": "Errors per component: runs (grey), filter 3-sigma (red dashed), sample 3-sigma (green)",
    "block_norms.png": "Error norm per block: runs (grey), RMSE (blue), filter 3-sigma (red dashed)",
    "nees_nis.png": "Mean NEES and NIS with their chi-square 95 % bands",
    "rmse_vs_pcrlb.png": "Monte Carlo RMSE against the posterior Cramer-Rao lower bound",
}
SWEEP_CAPTION = ("Rate sweep: settled RMSE per block (blue) and the PCRLB (black dashed) against the filter rate, "
                 "and the share of diverged runs (red)")


@locks_output("out", "report", folder=False)
def write_report(dirs: list[str], out: str) -> dict:
    """The report over the campaign and rate-sweep folders `dirs`, written atomically to out (.html; its folder
    made when every input reads). Returns {"campaigns": n, "sweeps": n, "notes": the fields a campaign's table
    or a sweep's shows as n/a, each named with its file and why (campaign_gaps, sweep_gaps), also warned}.
    InputError naming `out` or the folder."""

    dirs, out = paths_arg(dirs, "dirs"), path_arg(out, "out")
    if not out.endswith((".html", ".htm")):
        raise InputError(f"out {out!r}: expected a path ending in .html")
    check_out_file(out, "out")
    check_campaign_dirs(dirs)
    sweeps = [load_sweep(d) for d in dirs if is_sweep(d)]
    campaigns = [load_campaign(d) for d in dirs if not is_sweep(d)]
    make_out_file_dirs({out: "out"})
    atomic_write_text(out, render_report(campaigns, sweeps))
    notes = [note for c in campaigns for note in campaign_gaps(c)] + [note for c in sweeps for note in sweep_gaps(c)]
    unlike = unlike_notes(campaigns)
    for note in notes + unlike:  # the page's notes, said where the command runs too (the verb: one warning line each)
        warnings.warn(note, stacklevel=2)
    return {"campaigns": len(campaigns), "sweeps": len(sweeps), "notes": notes, "unlike": unlike}


def check_campaign_dirs(dirs: list[str]) -> None:
    """Each folder exists, is a folder and is given once (two columns of one campaign compare nothing): else
    InputError naming the folder, before anything is read."""
    seen: dict[str, str] = {}
    for d in dirs:
        if not os.path.exists(d):
            raise InputError(f"{d!r}: no such folder; expected a campaign folder of `envisat montecarlo --out`")
        if not os.path.isdir(d):
            raise InputError(f"{d!r} is a file; expected a campaign folder of `envisat montecarlo --out`")
        real = os.path.realpath(d)
        if real in seen:
            raise InputError(f"{d!r} is the folder {seen[real]!r} again (one column per campaign); give it once")
        seen[real] = d


def is_sweep(out_dir: str) -> bool:
    """A rate-sweep folder (`envisat montecarlo` with a sweep): sweep.json, one campaign folder per rate."""
    return os.path.isfile(os.path.join(out_dir, "sweep.json"))


def load_sweep(out_dir: str) -> dict:
    """What the report shows of a rate sweep: sweep.json, its figure and its config text."""
    path = os.path.join(out_dir, "sweep.json")
    sweep = _read_json(path)
    if not isinstance(sweep, dict) or "rates_hz" not in sweep:
        raise InputError(f"{path}: unreadable or not a rate sweep's summary")
    fig = os.path.join(out_dir, SWEEP_FIGURE)
    figure = ""
    if os.path.isfile(fig):
        with open(fig, "rb") as fh:
            figure = base64.b64encode(fh.read()).decode("ascii")
    config = _read_text(os.path.join(out_dir, CONFIG_NAME))
    c = {"dir": out_dir, "sweep": sweep, "figure": figure, "config": config}
    _readable(path, render_sweep, c)
    return c


def _readable(path: str, render, c: dict) -> None:
    """InputError naming the file when what it holds is JSON of another shape (a field missing, a list for a
    table, a string for a number): render(c) tried before anything is written."""
    if not isinstance(c.get("summary", c.get("sweep")), dict):
        raise InputError(f"{path}: not a summary this report reads (a JSON object expected)")
    try:
        render(c)
    except (KeyError, TypeError, AttributeError, IndexError, ValueError) as err:
        raise InputError(f"{path}: not a summary this report reads ({type(err).__name__}: {err})") from None


def unjudged_note(s: dict) -> str:
    """', N not judged (why)' for a campaign summary whose runs were too short for the divergence rule
    (n_unjudged: state.nees_window_judged), else '' (and for a summary written before the field)."""
    n = s.get("n_unjudged") or 0
    if not n:
        return ""
    why = unjudged_why(s.get("steps"), s.get("divergence_settle_steps"), s.get("divergence_window"))
    return f", {n} not judged ({why})"


def render_sweep(c: dict) -> str:
    """One rate sweep: a table with a row per rate (RMSE and RMSE/PCRLB per block, diverged runs, NEES,
    converged) and its figure."""
    e, s = html.escape, c["sweep"]
    head = ["rate (Hz)"] + [f"RMSE {b} ({DISPLAY[b][0]})" for b in BLOCKS] + [f"RMSE / PCRLB {b}" for b in BLOCKS]
    head += ["diverged runs", "mean NEES", "converged"]
    rows, alone = [], s.get("n_nis_alarm_alone") or [0] * len(s["rates_hz"])  # a sweep.json before they were named
    unjudged = s.get("n_unjudged") or [0] * len(s["rates_hz"])
    for i, rate in enumerate(s["rates_hz"]):
        cells = [f"{rate:g}"] + [_said(s["rmse"][b][i], _fmt(s["rmse"][b][i], DISPLAY[b][1])) for b in BLOCKS]
        cells += [_said(s["rmse_over_pcrlb"][b][i], _ratio(s["rmse_over_pcrlb"][b][i])) for b in BLOCKS]
        cells += [f"{s['n_diverged'][i]} / {s['runs']}"
                  + (f" ({alone[i]} flagged by the filter alone)" if alone[i] else "")
                  + (f", {unjudged[i]} not judged (runs too short)" if unjudged[i] else ""),
                  _said(s["nees_mean"][i], _fmt(s["nees_mean"][i])), "yes" if s["converged"][i] else "no"]
        rows.append("<tr>" + "".join(f"<td>{e(v)}</td>" for v in cells) + "</tr>")
    low = s.get("lowest_converged_rate_hz")
    rule = ("diverged against the truth, the NIS monitor's lone alarms aside" if "n_nis_alarm_alone" in s
            else "flagged diverged")
    verdict = (f"Converges (at most {_fmt(s.get('max_diverged_share'), 100.0)} % of runs {rule}, RMSE / "
               f"PCRLB below {s.get('max_rmse_over_pcrlb')} in every block) at "
               f"every rate down to {low:g} Hz." if low is not None else "Does not converge at the fastest rate.")
    fig = (f"<figure><img alt=\"{SWEEP_FIGURE}\" src=\"data:image/png;base64,{c['figure']}\"><figcaption>"
           f"{e(SWEEP_CAPTION)}</figcaption></figure>" if c["figure"] else "")
    name = os.path.basename(os.path.normpath(c["dir"])) or c["dir"]
    target = (s.get("target") or {}).get("name") or campaign_target(c["config"])
    return (f"<h2>Rate sweep {e(name)}</h2><p>{e(c['dir'])}: target {e(str(target))}, scenario "
            f"{e(str(s.get('scenario')))}, "
            f"{s.get('runs')} runs per rate over {_fmt(s.get('duration_s'))} s, seed {s.get('seed')}, statistics "
            f"after {_fmt(s.get('settle_s'))} s. {e(verdict)}</p><table><tr>"
            + "".join(f"<th>{e(h)}</th>" for h in head) + "</tr>" + "".join(rows) + "</table>"
            + _gap_notes(sweep_gaps(c)) + fig
            + f"<details><summary>config</summary><pre>{e(c['config'])}</pre></details>")


def load_campaign(out_dir: str) -> dict:
    """What the report shows of one folder: summary.json, timing.json (optional), the config text, the PNGs."""
    path = os.path.join(out_dir, "summary.json")
    if not os.path.isfile(path):
        raise InputError(unfinished_why(out_dir))
    try:
        with open(path, encoding="utf-8") as fh:
            summary = json.load(fh)
    except (OSError, ValueError) as err:
        raise InputError(f"{path}: unreadable ({err})") from None
    timing = _read_json(os.path.join(out_dir, "timing.json"))
    config = _read_text(os.path.join(out_dir, CONFIG_NAME)) or _read_text(os.path.join(out_dir, SWEEP_RATE_CONFIG))
    figures = {}
    for name in FIGURE_CAPTIONS:
        fig = os.path.join(out_dir, name)
        if os.path.isfile(fig):
            with open(fig, "rb") as fh:
                figures[name] = base64.b64encode(fh.read()).decode("ascii")
    c = {"dir": out_dir, "summary": summary, "timing": timing, "config": config, "figures": figures}
    _readable(path, campaign_rows, c)
    return c


def unfinished_why(out_dir: str) -> str:
    """The one line for a folder without summary.json or sweep.json: an interrupted campaign (its manifest says
    how many blocks are done; rerun its command to finish it), an unfinished rate sweep (rate-<R>hz folders), or
    no `envisat montecarlo` folder at all (rerunning a command would not make one)."""
    manifest = read_manifest(out_dir, "dirs")  # an unreadable one: InputError naming it
    if manifest is not None and manifest.get("format") == MANIFEST_FORMAT:
        blocks = manifest.get("blocks")
        done = f"{len(blocks)} of {manifest.get('n_blocks', '?')} blocks done, " if isinstance(blocks, list) else ""
        return (f"{out_dir!r} is an interrupted `envisat montecarlo` campaign ({done}no summary.json yet): rerun "
                "its command to finish it")
    if any(n.startswith("rate-") and n.endswith("hz") for n in os.listdir(out_dir)):
        return (f"{out_dir!r} is an unfinished rate sweep (rate-<R>hz folders, no sweep.json yet): rerun its "
                "command to finish it")
    return (f"{out_dir!r} is not an `envisat montecarlo` folder: no summary.json, sweep.json or a campaign's "
            "manifest.json in it")


def _read_text(path: str) -> str:
    """A folder's text file ('' where there is none)."""
    if not os.path.isfile(path):
        return ""
    with open(path, encoding="utf-8") as fh:
        return fh.read()


def _read_json(path: str) -> dict:
    try:
        with open(path, encoding="utf-8") as fh:
            return json.load(fh)
    except (OSError, ValueError):
        return {}


def _fmt(v, scale: float = 1.0, digits: int = 4) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "n/a"
    return f"{v * scale:.{digits}g}"


def _ratio(v) -> str:
    """RMSE / PCRLB to three decimals, as `envisat montecarlo` prints it (1.103, not 1.1: ratios sit near 1)."""
    return "n/a" if _fmt(v) == "n/a" else f"{v:.3f}"


def config_differences(campaigns: list[dict]) -> list[str]:
    """Per campaign, its config values that differ between the campaigns ('' for one campaign)."""
    flat = []
    for c in campaigns:
        try:
            flat.append(flatten(tomllib.loads(c["config"])))
        except tomllib.TOMLDecodeError:
            flat.append({})
    keys = sorted({k for f in flat for k in f if len({repr(g.get(k)) for g in flat}) > 1})
    return ["; ".join(f"{k} = {f.get(k, 'unset')}" for k in keys) for f in flat]




def campaign_target(config_text: str) -> str:
    """The target file a campaign's config names (its file name; ENVISAT's default where it names none)."""
    try:
        given = tomllib.loads(config_text).get("target") if config_text else None
    except tomllib.TOMLDecodeError:
        given = None
    return os.path.basename(str(given or DEFAULT_TARGET))


def summary_target(summary: dict, config_text: str) -> str:
    """The campaign's target as its summary.json records it (the MJCF model's name: a scenario file's
    `[target] file` too, which the campaign's config does not name), else the file its config names."""
    recorded = summary.get("target")
    name = recorded.get("name") if isinstance(recorded, dict) else None
    return str(name) if name else campaign_target(config_text)


def target_values(campaigns: list[dict]) -> list[str]:
    """Each campaign's target as the like-for-like note compares it: its name (summary_target), with its sha256's
    first 12 digits where campaigns of that name record other sha256s (a user's edited craft keeps its MJCF
    model name: another inertia or keypoints under one name). A summary without a sha256 (written before the
    field) is compared by its name alone."""
    names = [summary_target(c["summary"], c["config"]) for c in campaigns]
    records = [c["summary"].get("target") for c in campaigns]
    shas = [r.get("sha256") if isinstance(r, dict) else None for r in records]
    edited = {n for n in names if len({s for m, s in zip(names, shas) if m == n and s}) > 1}
    return [f"{n} (sha256 {s[:12]}...)" if n in edited and s else n for n, s in zip(names, shas)]


# what two campaigns side by side must share for their columns to compare the filter alone: (what, their values)
LIKE_FOR_LIKE = (("target", target_values),
                 ("duration", lambda cs: [f"{_fmt(c['summary'].get('duration_s'))} s" for c in cs]),
                 ("settle time (statistics after)", lambda cs: [f"{_fmt(c['summary'].get('settle_s'))} s" for c in cs]))


def unlike_notes(campaigns: list[dict]) -> list[str]:
    """One line per quantity of LIKE_FOR_LIKE that differs between the campaigns, naming each column's value:
    their RMSE then describes another body or span, so only each one's RMSE / PCRLB and NEES (against its own
    bound and band) compare. [] for one campaign or campaigns that agree."""
    if len(campaigns) < 2:
        return []
    names, notes = column_names([c["dir"] for c in campaigns]), []
    for what, values_of in LIKE_FOR_LIKE:
        values = values_of(campaigns)
        if len(set(values)) > 1:
            shown = ", ".join(f"{n}: {v}" for n, v in zip(names, values))
            notes.append(f"not like for like: the campaigns differ in {what} ({shown}); their RMSE does not compare "
                         "across columns, only each one's RMSE / PCRLB and NEES against its own bound and band")
    return notes


BLOCK_TABLES = ("rmse", "pcrlb_rms", "rmse_over_pcrlb", "inside_3sigma_share")  # summary.json's per-block tables
SCALARS = ("nees_mean", "nis_mean_per_dof")


def why_missing(table, key: str) -> str | None:
    """Why the summary's table[key] shows as n/a: 'missing' (no such key, or no table), 'null', 'nan' or 'inf'
    (a non-finite number); None where it holds a number (or another value the table refuses)."""
    if not isinstance(table, dict) or key not in table:
        return "missing"
    return why_not_a_number(table[key])


def why_not_a_number(v) -> str | None:
    """Why a value shows as n/a: 'null', 'nan' or 'inf' (a non-finite number); None for any other value."""
    if v is None:
        return "null"
    return str(v) if isinstance(v, float) and not math.isfinite(v) else None


def _said(v, text: str) -> str:
    """A sweep table's cell: its text, and where it reads n/a, why (sweep_gaps names the field, rate and file)."""
    why = why_not_a_number(v)
    return f"{text} ({why})" if why and text.startswith("n/a") else text


def sweep_gaps(c: dict) -> list[str]:
    """One line per cell of a rate sweep's table that shows as n/a: sweep.json's field (table.block), the rate, why
    (why_not_a_number) and the rate's campaign whose summary.json it was copied from (the sweep writes a value that
    was not finite there, NaN or infinite, as null; that campaign's own report row names it too)."""
    s, path, gaps = c["sweep"], os.path.join(c["dir"], "sweep.json"), []
    folders = s.get("campaigns") or [None] * len(s["rates_hz"])
    for i, rate in enumerate(s["rates_hz"]):
        fields = [(f"{name}.{b}", s[name][b][i]) for name in ("rmse", "rmse_over_pcrlb") for b in BLOCKS]
        whys = [(field, why) for field, v in fields + [("nees_mean", s["nees_mean"][i])]
                if (why := why_not_a_number(v))]
        source = f"not finite in {os.path.join(c['dir'], folders[i], 'summary.json')}" if folders[i] else ""
        gaps += [f"{path}: {field} at {rate:g} Hz {why} (shown as n/a{'; ' + source if source else ''})"
                 for field, why in whys]
    return gaps


def _gap_notes(gaps: list[str]) -> str:
    """The page's list of the fields shown as n/a (empty without any)."""
    return ("<p>Shown as n/a:</p><ul class=\"notes\">" + "".join(f"<li>{html.escape(g)}</li>" for g in gaps)
            + "</ul>") if gaps else ""


def _cell(table, key: str, text: str) -> str:
    """A table's cell: its text, and where it reads n/a for a field the summary lacks, why (campaign_gaps names
    the field and the file)."""
    why = why_missing(table, key)
    return f"{text} ({why})" if why and text.startswith("n/a") else text


def campaign_gaps(c: dict) -> list[str]:
    """One line per field of the campaign's summary.json (or its timing.json) that its table shows as n/a: the
    file, the field (table.block) and why (why_missing). A whole table missing is one line."""
    s, path, gaps = c["summary"], os.path.join(c["dir"], "summary.json"), []
    for name in BLOCK_TABLES:
        table = s.get(name)
        if not isinstance(table, dict):
            gaps.append(f"{path}: no {name} (its rows show n/a)")
            continue
        gaps += [f"{path}: {name}.{b} {why} (shown as n/a)" for b in BLOCKS if (why := why_missing(table, b))]
    gaps += [f"{path}: {k} {why} (shown as n/a)" for k in SCALARS if (why := why_missing(s, k))]
    if not c["timing"]:
        gaps.append(f"{os.path.join(c['dir'], 'timing.json')}: missing or unreadable (wall time shown as n/a)")
    return gaps


def campaign_rows(c: dict) -> list[tuple[str, str]]:
    """(label, value) rows of one campaign's table, already formatted."""
    s, t = c["summary"], c["timing"]
    m = s.get("measurement", {})
    noise = f"{m.get('sigma_m')} m" if m.get("kind") == "markers3d" else f"{m.get('sigma_px')} px"
    markers = "all visible" if m.get("max_markers") is None else f"at most {m['max_markers']}"
    rows = [("scenario", str(s.get("scenario"))), ("target", summary_target(s, c["config"])),
            ("runs x steps", f"{s.get('runs')} x {s.get('steps')}"),
            ("duration", _cell(s, "duration_s", f"{_fmt(s.get('duration_s'))} s")),
            ("measurements", f"{m.get('kind')}, {noise}, {m.get('rate_hz')} Hz, {markers} keypoints"),
            ("seed", str(s.get("seed"))), ("statistics after", f"{_fmt(s.get('settle_s'))} s")]
    for b in BLOCKS:
        unit, k = DISPLAY[b]
        rows.append((f"RMSE {b} ({unit})", _cell(s["rmse"], b, _fmt(s["rmse"].get(b), k))))
    for b in BLOCKS:
        unit, k = DISPLAY[b]
        rows.append((f"PCRLB {b} ({unit})", _cell(s.get("pcrlb_rms"), b, _fmt(s.get("pcrlb_rms", {}).get(b), k))))
    for b in BLOCKS:
        ratio = s.get("rmse_over_pcrlb")
        rows.append((f"RMSE / PCRLB {b}", _cell(ratio, b, _ratio((ratio or {}).get(b)))))
    for b in BLOCKS:
        share = s["inside_3sigma_share"]
        rows.append((f"inside 3-sigma {b}", _cell(share, b, f"{_fmt(share.get(b), 100.0, 4)} %")))
    lo, hi = s.get("nees_bounds", [None, None])
    band = f"95 % band {_fmt(lo)} .. {_fmt(hi)} if every step were independent"  # an older summary's one band
    if "nees_run_bounds" in s:  # the band a consistent campaign lies within first
        band = f"95 % band {_fmt(s['nees_run_bounds'][0])} .. {_fmt(s['nees_run_bounds'][1])} with one sample a " \
               f"run; {_fmt(lo)} .. {_fmt(hi)} if every step were independent"
    rows += [("mean NEES (12 dof)", f"{_cell(s, 'nees_mean', _fmt(s.get('nees_mean')))} ({band})"),
             ("NIS per dof", _cell(s, "nis_mean_per_dof", _fmt(s.get("nis_mean_per_dof")))),
             ("diverged runs", f"{s.get('n_diverged')} / {s.get('n_runs')}" + (
                 f" ({len(s['nis_alarm_alone_runs'])} flagged by the filter alone, their errors within the "
                 "NEES rule)"
                 if s.get("nis_alarm_alone_runs") else "") + unjudged_note(s)),
             ("wall time", wall_time_cell(t))]
    return rows


def wall_time_cell(t: dict) -> str:
    """The wall-time cell from timing.json's dict: the blocks' summed wall time, the last invocation's and its
    workers ('1 local worker', '4 local workers'); n/a without timing.json."""
    if not t:
        return "n/a (no timing.json)"
    n = t.get("workers", "?")
    return (f"{_fmt(t.get('block_wall_s_sum'), digits=4)} s in blocks, "
            f"{_fmt(t.get('wall_s_this_invocation'), digits=4)} s last invocation "
            f"({n} {t.get('backend', '?')} worker{'' if n == 1 else 's'})")


STYLE = """body{font-family:sans-serif;margin:1em}table{border-collapse:collapse}td,th{border:1px solid #bbb;
padding:2px 6px;text-align:right;vertical-align:top}th{background:#eee}td.l{text-align:left}
.cols{display:flex;gap:1em;align-items:flex-start}.col{flex:1;min-width:0}img{width:100%;height:auto}
pre{font-size:11px;background:#f6f6f6;padding:4px;overflow-x:auto}ul.unlike{color:#a40;font-weight:bold}"""


def render_report(campaigns: list[dict], sweeps: list[dict] = ()) -> str:
    """The whole HTML page: a comparison table (one column per campaign), then per campaign its figures and
    config, side by side, then each rate sweep (render_sweep). Every figure is a data:image/png;base64 URI."""
    e = html.escape
    sweeps_html = "".join(render_sweep(c) for c in sweeps)
    if not campaigns:
        return _page(sweeps_html)
    names = column_names([c["dir"] for c in campaigns])
    unlike = unlike_notes(campaigns)
    table = ["<ul class=\"unlike\">" + "".join(f"<li>{e(n)}</li>" for n in unlike) + "</ul>"] if unlike else []
    table += ["<table><tr><th></th>" + "".join(f"<th>{e(n)}</th>" for n in names) + "</tr>"]
    all_rows = [campaign_rows(c) for c in campaigns]
    if len(campaigns) > 1:
        all_rows = [[("config differences", d)] + rows for d, rows in zip(config_differences(campaigns), all_rows)]
    for i, (label, _) in enumerate(all_rows[0]):
        cells = "".join(f"<td>{e(rows[i][1])}</td>" for rows in all_rows)
        table.append(f"<tr><td class=\"l\">{e(label)}</td>{cells}</tr>")
    table.append("</table>")
    gaps = [(n, g) for n, c in zip(names, campaigns) for g in campaign_gaps(c)]
    if gaps:  # the n/a cells' fields, by campaign and file
        table.append("<p>Shown as n/a:</p><ul class=\"notes\">"
                     + "".join(f"<li>{e(n)}: {e(g)}</li>" for n, g in gaps) + "</ul>")
    cols = []
    for n, c in zip(names, campaigns):
        figs = "".join(f"<figure><img alt=\"{e(name)}\" src=\"data:image/png;base64,{data}\">"
                       f"<figcaption>{e(FIGURE_CAPTIONS[name])}</figcaption></figure>"
                       for name, data in c["figures"].items())
        cols.append(f"<div class=\"col\"><h2>{e(n)}</h2><p>{e(c['dir'])}</p>{figs}"
                    f"<details><summary>config</summary><pre>{e(c['config'])}</pre></details></div>")
    return _page("\n".join(table) + "<div class=\"cols\">" + "".join(cols) + "</div>" + sweeps_html)


def column_names(dirs: list[str]) -> list[str]:
    """Each folder's shortest trailing path that no other folder of the report shares (mc/us and mc/cs as 'us'
    and 'cs'; tg/upper_stage/mc and tg/cubesat_3u/mc as 'upper_stage/mc' and 'cubesat_3u/mc')."""
    parts = [os.path.normpath(os.path.abspath(d)).split(os.sep) for d in dirs]
    names = []
    for p in parts:
        for k in range(1, len(p) + 1):
            tail = p[-k:]
            if sum(q[-k:] == tail for q in parts) == 1 or k == len(p):
                names.append("/".join(tail).lstrip("/") or os.sep)
                break
    return names


def _page(body: str) -> str:
    return ("<!DOCTYPE html>\n<html><head><meta charset=\"utf-8\"><title>envisat Monte Carlo report</title>"
            f"<style>{STYLE}</style></head><body><h1>Monte Carlo campaigns</h1>"
            "<p>Statistics over the run-steps after the settle time; RMSE / PCRLB is the ratio of the RMS over time "
            "of the Monte Carlo RMSE and of the posterior Cramer-Rao lower bound (1: the best any unbiased "
            "estimator can do). A consistent campaign's mean NEES lies within the band with one sample a run; the band "
            "with every step independent is narrower than the campaign's spread (a run's errors are correlated in "
            "time).</p>"
            + body + "</body></html>\n")
