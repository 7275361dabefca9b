"""What the status pages show, rendered from a :class:`~drivetrack.release.status.ReleaseStatus`:
the self-contained ``status.html`` (inline CSS, no scripts, no network), the quality read from a
release's tables and gate report, the Prefect markdown summaries and the version index page.
Pure core (no Prefect).
"""
from __future__ import annotations

import html
import json
from dataclasses import dataclass, field

import fsspec

from drivetrack.release.status import (SEGMENT_STAGES, ReleaseStatus, SegmentStatus, StageStatus, StatusError,
                                       _utc)

__all__ = ["render_status_html", "safe_release_href", "PREVIEW_TYPES", "ReleaseQuality", "read_quality",
           "segment_markdown", "reused_markdown", "render_index_html"]

_COLOURS = {  # state -> (background, text)
    "pending": ("#e9ecef", "#495057"),
    "running": ("#cfe2ff", "#084298"),
    "done": ("#d1e7dd", "#0f5132"),
    "failed": ("#f8d7da", "#842029"),
    "skipped": ("#fff3cd", "#664d03"),
}


# ---- HTML --------------------------------------------------------------------------------------

_CSS = """
body{font-family:-apple-system,"Segoe UI",Roboto,Helvetica,Arial,sans-serif;margin:24px;color:#212529;background:#fff}
h1{font-size:22px;margin:0 0 4px}
.meta{color:#6c757d;font-size:13px;margin-bottom:16px}
.meta code{background:#f1f3f5;padding:1px 4px;border-radius:3px}
.chips{display:flex;gap:8px;flex-wrap:wrap;margin:12px 0}
.chip{padding:6px 12px;border-radius:14px;font-weight:600;font-size:14px}
table{border-collapse:collapse;width:100%;font-size:13px}
th,td{border:1px solid #dee2e6;padding:6px 8px;text-align:left;vertical-align:top}
th{background:#f8f9fa}
td.st,td.nw{white-space:nowrap}
.gate{margin-bottom:4px}.gate .small{font-family:ui-monospace,Menlo,Consolas,monospace}
.ok{color:#0f5132}
.small{font-size:11px;opacity:.85}
.err{font-family:ui-monospace,Menlo,Consolas,monospace;font-size:12px;color:#842029;white-space:pre-wrap;word-break:break-word}
.legend span{display:inline-block;padding:2px 8px;border-radius:3px;margin-right:6px;font-size:12px}
h2{font-size:16px;margin:22px 0 8px}
"""


def _cell(st: StageStatus) -> str:
    e = html.escape
    bg, fg = _COLOURS[st.state]
    bits = [f"<b>{html.escape(st.state)}</b>"]
    if st.cached:
        bits.append("cached")
    details = []
    if st.count is not None:
        details.append(f"{e(str(st.count))} {e(st.unit or '')}".rstrip())
    if isinstance(st.seconds, (int, float)):
        details.append(f"{st.seconds:.2f} s")
    if st.completer:
        details.append(e(st.completer) + (f" on {e(st.device)}" if st.device else ""))
    if st.worker:
        details.append(html.escape(st.worker))
    inner = " ".join(bits) + (f'<div class="small">{" · ".join(details)}</div>' if details else "")
    title = f' title="{html.escape(st.error)}"' if st.error else ""
    return f'<td class="st" data-state="{e(st.state)}" style="background:{bg};color:{fg}"{title}>{inner}</td>'


#: Preview files the page shows and ``drivetrack status`` serves, by suffix -> content type.
PREVIEW_TYPES = {".png": "image/png", ".jpg": "image/jpeg", ".jpeg": "image/jpeg", ".gif": "image/gif",
                 ".webp": "image/webp", ".mp4": "video/mp4", ".webm": "video/webm"}


def safe_release_href(path, under: str | None = None) -> str | None:
    """``path`` when it is a relative path inside the release (``names.py`` kind ``release_file``:
    no scheme such as ``javascript:``, no ``//host``, no leading ``/``, no ``..`` or hidden part),
    and below the folder ``under`` when given; else None (the page drops the link)."""
    from drivetrack.names import is_valid_name

    if not is_valid_name("release_file", path):
        return None
    if under is not None and not path.startswith(under.rstrip("/") + "/"):
        return None
    return path


def _previews_html(previews: list[str]) -> str:
    """Links to the release's previews (paths relative to the release folder the page sits in).
    Only files under ``previews/`` with a known suffix are linked; anything else is listed as
    refused text, never as a link."""
    if not previews:
        return ""
    e = html.escape
    items, refused = [], []
    for p in previews:
        href = safe_release_href(p, under="previews")
        suffix = "." + href.rsplit(".", 1)[-1].lower() if href and "." in href else ""
        if href is None or suffix not in PREVIEW_TYPES:
            refused.append(p)
        elif PREVIEW_TYPES[suffix].startswith("image/"):
            items.append(f'<a href="{e(href)}"><img src="{e(href)}" alt="{e(href)}" '
                         f'style="max-width:420px;margin:4px"></a>')
        else:
            items.append(f'<p><a href="{e(href)}">clip: {e(href)}</a></p>')
    note = (f'<p class="err">not linked (not a file under previews/): {e(", ".join(map(str, refused)))}</p>'
            if refused else "")
    return f"<h2>Previews</h2>\n<div>{''.join(items)}</div>{note}"


def render_status_html(status: ReleaseStatus, *, refresh_s: int | None = None,
                       quality: ReleaseQuality | None = None) -> str:
    """A self-contained HTML page: summary counts, release stages, one row per segment with one
    coloured cell per stage (state, count, duration, worker), its quality (``quality``: clips,
    tracks, speed-error p50, refined share, rejected clips by reason, failing gates with their
    values) and the error. ``refresh_s`` adds a meta refresh, for a page watched while the build
    runs. Everything taken from data is HTML-escaped; links are relative paths inside the
    release or dropped (:func:`safe_release_href`)."""
    e = html.escape
    if quality is not None and not quality.segments and quality.gates_success is None:
        quality = None  # no tables, no gate report (a build still running, or a bare status)
    counts = status.counts()
    chips = "".join(
        f'<span class="chip" data-count="{k}" style="background:{_COLOURS[k][0]};color:{_COLOURS[k][1]}">'
        f'{e(k)}: {n}</span>' for k, n in counts.items())
    rel_cells = "".join(_cell(st) for st in status.stages.values())
    rel_head = "".join(f"<th>{e(k)}</th>" for k in status.stages)
    stage_names = list(SEGMENT_STAGES)
    for seg in status.segments:
        stage_names += [k for k in seg.stages if k not in stage_names]
    seg_head = "".join(f"<th>{e(k)}</th>" for k in stage_names)
    rows = []
    for seg in status.segments:
        bg, fg = _COLOURS[seg.state]
        cells = "".join(_cell(seg.stages[k]) if k in seg.stages else "<td></td>" for k in stage_names)
        rows.append(
            f'<tr data-segment="{e(seg.segment)}" data-state="{seg.state}">'
            f"<td>{e(seg.split)}</td><td class=\"nw\"><code>{e(seg.segment)}</code></td>"
            f'<td class="st" style="background:{bg};color:{fg}"><b>{seg.state}</b>'
            f'{" (cached)" if seg.cached and seg.state == "done" else ""}</td>'
            f"<td class=\"nw\">{seg.seconds:.2f} s</td>{cells}"
            + (_quality_cells(quality.of(seg.split, seg.segment)) if quality is not None else "") +
            f'<td class="err">{e(seg.error or "")}</td></tr>')
    q_head = ("<th>clips</th><th>tracks</th><th>speed err p50</th><th>refined</th><th>rejected clips</th>"
              "<th>failing gates</th>") if quality is not None else ""
    legend = "".join(f'<span style="background:{b};color:{f}">{s}</span>' for s, (b, f) in _COLOURS.items())
    refresh = f'<meta http-equiv="refresh" content="{int(refresh_s)}">' if refresh_s else ""
    published = "published" if status.published else "not published"
    message = f'<p class="meta">{e(status.message)}</p>' if status.message else ""
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8">{refresh}
<title>{e(status.dataset)} {e(status.version)}: release status</title>
<style>{_CSS}</style></head>
<body>
<h1>{e(status.dataset)} {e(status.version)} <span class="chip" style="background:{_COLOURS[status.state][0]};color:{_COLOURS[status.state][1]}">{status.state}, {published}</span></h1>
<div class="meta">source <code>{e(status.source or "-")}</code> · store <code>{e(status.store or "-")}</code>
 · started {e(_utc(status.created) or "-")} · updated {e(_utc(status.updated) or "-")}
 · fingerprint <code>{e((status.fingerprint or "-")[:16])}</code></div>
{message}
<div class="chips">{chips}<span class="chip" style="background:#f1f3f5">segments: {len(status.segments)}</span></div>
<h2>Release stages</h2>
<table><tr>{rel_head}</tr><tr>{rel_cells}</tr></table>
<h2>Segments</h2>
<table id="segments"><tr><th>split</th><th>segment</th><th>state</th><th>time</th>{seg_head}{q_head}<th>error</th></tr>
{"".join(rows) or '<tr><td colspan="99">no segments</td></tr>'}
</table>
<p class="legend">{legend}</p>
{_release_gates_html(quality)}
{_previews_html(status.previews)}
</body></html>
"""


# ---- quality (stats/*.parquet, validation/gates.json) -----------------------------------------

@dataclass
class ReleaseQuality:
    """Quality of a built release, per segment, beside its state.

    ``segments[(split, segment)]``: ``clips`` (``num_object_clips_annotated``), ``tracks``
    (``num_tracks``) from ``stats/segments.parquet``; ``speed_err_p50`` (m/s, median over the
    segment's clips of their ``speed_err_p50``) and ``refined_share`` (share of its clips with
    ``refine_applied``; None without pose refinement) from ``stats/objects.parquet``;
    ``rejected`` (reason -> clips, the non-zero ``rejected_<reason>`` columns); ``gates``: the
    failing gates whose failing rows name the segment, each ``{gate, expected, num_failing,
    values}`` (``values``: up to 5 ``"object: column=value"`` strings).
    ``gates_success``: the verdict of ``validation/gates.json`` (None without one);
    ``release_gates``: failing gates not attributable to one segment (``{gate, observed, expected}``).
    """
    segments: dict = field(default_factory=dict)
    gates_success: bool | None = None
    gates_failed: int = 0
    gates_total: int = 0
    release_gates: list = field(default_factory=list)

    def of(self, split: str, segment: str) -> dict | None:
        return self.segments.get((split, segment))


def _num(v) -> float | None:
    try:
        f = float(v)
    except (TypeError, ValueError):
        return None
    return f if f == f and abs(f) != float("inf") else None


def _short(v) -> str:
    f = _num(v) if not isinstance(v, (str, bool)) else None
    return f"{f:.4g}" if f is not None else str(v)[:80]


def read_quality(release_url: str, *, storage_options: dict | None = None) -> ReleaseQuality:
    """The :class:`ReleaseQuality` of a release or annotation folder (any fsspec URL); tables or
    a gate report that are missing leave their fields empty. Unreadable files raise naming them."""
    import io

    import pandas as pd

    fs, root = fsspec.core.url_to_fs(str(release_url), **(storage_options or {}))
    root = root.rstrip("/")
    q = ReleaseQuality()

    def table(name: str):
        path = f"{root}/stats/{name}.parquet"
        if not fs.exists(path):
            return None
        try:
            return pd.read_parquet(io.BytesIO(fs.cat_file(path)))
        except Exception as e:  # noqa: BLE001 - the message names the file
            raise StatusError(f"{path}: not a readable parquet table ({type(e).__name__}: {e})") from e

    segs, objs = table("segments"), table("objects")
    if segs is not None and {"split", "segment"} <= set(segs.columns):
        reasons = [c for c in segs.columns if c.startswith("rejected_")]
        for row in segs.to_dict("records"):
            key = (str(row["split"]), str(row["segment"]))
            rejected = {c[len("rejected_"):]: int(_num(row[c]) or 0) for c in reasons if _num(row[c])}
            q.segments[key] = {"status": row.get("status"), "clips": _num(row.get("num_object_clips_annotated")),
                               "tracks": _num(row.get("num_tracks")), "speed_err_p50": None,
                               "refined_share": None, "rejected": rejected, "gates": []}
    if objs is not None and {"split", "segment"} <= set(objs.columns) and len(objs):
        grouped = objs.groupby(["split", "segment"], sort=False)
        for (split, segment), g in grouped:
            d = q.segments.setdefault((str(split), str(segment)), {
                "status": None, "clips": float(len(g)), "tracks": None, "speed_err_p50": None,
                "refined_share": None, "rejected": {}, "gates": []})
            if "speed_err_p50" in g:
                d["speed_err_p50"] = _num(pd.to_numeric(g["speed_err_p50"], errors="coerce").median())
            if "refine_applied" in g:
                applied = g["refine_applied"].map(lambda v: v is True or v == 1 or v == "True")
                d["refined_share"] = float(applied.mean())
    gates_path = f"{root}/validation/gates.json"
    if fs.exists(gates_path):
        try:
            report = json.loads(fs.cat_file(gates_path))
        except ValueError as e:
            raise StatusError(f"{gates_path}: not valid JSON ({e})") from e
        results = [r for r in (report.get("results") or []) if isinstance(r, dict)] if isinstance(report, dict) else []
        q.gates_success = bool(report.get("success")) if isinstance(report, dict) else None
        q.gates_total = len(results)
        for r in results:
            if r.get("success", True):
                continue
            q.gates_failed += 1
            _attribute_gate(q, r)
    return q


def _expected(r: dict) -> str:
    from drivetrack.gates.report import expected_text

    exp = r.get("expected")
    try:
        return expected_text(exp) if isinstance(exp, dict) else str(exp or "")
    except Exception:  # noqa: BLE001 - a malformed bound is shown as it is
        return str(exp)


def _attribute_gate(q: ReleaseQuality, r: dict) -> None:
    """File one failing gate under the segments its failing rows name, or under the release."""
    gate = str(r.get("gate") or r.get("expectation") or "gate")
    columns = [str(c) for c in (r.get("columns") or []) if isinstance(c, str)]
    per_seg: dict = {}
    for row in r.get("failing") or []:
        if not isinstance(row, dict) or row.get("segment") is None:
            continue
        split, segment = row.get("split"), str(row["segment"])
        key = (str(split), segment) if split is not None else next(
            (k for k in q.segments if k[1] == segment), (None, segment))
        vals = ", ".join(f"{c}={_short(row[c])}" for c in columns if c in row)
        who = row.get("object_id") or row.get("camera")
        per_seg.setdefault(key, []).append(f"{who}: {vals}" if who else vals)
    if not per_seg:
        q.release_gates.append({"gate": gate, "observed": _short(r.get("observed")), "expected": _expected(r)})
        return
    for key, values in per_seg.items():
        d = q.segments.setdefault(key, {"status": None, "clips": None, "tracks": None, "speed_err_p50": None,
                                        "refined_share": None, "rejected": {}, "gates": []})
        d["gates"].append({"gate": gate, "expected": _expected(r), "num_failing": len(values),
                           "values": values[:5]})


def _quality_cells(q: dict | None) -> str:
    """The quality columns of one segment row: clips, tracks, speed-error p50, refined, rejected,
    failing gates (everything escaped)."""
    e = html.escape
    if q is None:
        return '<td class="q" colspan="6">no statistics</td>'

    def n(v, fmt="{:.0f}"):
        return e(fmt.format(v)) if isinstance(v, (int, float)) else "-"
    rejected = "<br>".join(f"{e(k)}: {int(v)}" for k, v in sorted(q["rejected"].items(), key=lambda kv: -kv[1]))
    gates = "".join(
        f'<div class="gate"><b>{e(g["gate"])}</b> <span class="small">expected {e(g["expected"])}; '
        f'{int(g["num_failing"])} failing</span><div class="small">{e("; ".join(g["values"]))}</div></div>'
        for g in q["gates"]) or '<span class="ok">none</span>'
    bad = ' style="background:#f8d7da"' if q["gates"] else ""
    return (f'<td class="nw" data-q="clips">{n(q["clips"])}</td><td class="nw" data-q="tracks">{n(q["tracks"])}</td>'
            f'<td class="nw" data-q="speed_err_p50">{n(q["speed_err_p50"], "{:.3g} m/s")}</td>'
            f'<td class="nw" data-q="refined">{n(None if q["refined_share"] is None else 100 * q["refined_share"], "{:.0f} %")}</td>'
            f'<td class="small" data-q="rejected">{rejected or "-"}</td><td data-q="gates"{bad}>{gates}</td>')


def _release_gates_html(quality: ReleaseQuality | None) -> str:
    if quality is None or quality.gates_success is None:
        return ""
    e = html.escape
    verdict = "passed" if quality.gates_success else "FAILED"
    colour = _COLOURS["done" if quality.gates_success else "failed"]
    rows = "".join(f"<tr><td><b>{e(g['gate'])}</b></td><td>{e(g['observed'])}</td><td>{e(g['expected'])}</td></tr>"
                   for g in quality.release_gates)
    table = (f'<table id="release-gates"><tr><th>failing release gate</th><th>observed</th><th>expected</th></tr>'
             f"{rows}</table>") if rows else ""
    return (f'<h2>Gates <span class="chip" style="background:{colour[0]};color:{colour[1]}">{verdict}: '
            f"{quality.gates_failed} of {quality.gates_total} failed</span></h2>{table}")


# ---- Prefect artifact text (markdown; the flow posts it) --------------------------------------

def _md(text) -> str:
    """Text safe inside a markdown table cell or line: no HTML, no pipes or newlines."""
    return html.escape(str(text)).replace("|", "\\|").replace("\n", " ").replace("`", "'")


def segment_markdown(status: ReleaseStatus, seg: SegmentStatus, quality: ReleaseQuality | None = None) -> str:
    """One segment's summary for a Prefect markdown artifact: its stages, clips, tracks, quality
    and gate results."""
    q = quality.of(seg.split, seg.segment) if quality else None
    lines = [f"# {_md(seg.split)}/{_md(seg.segment)}: {seg.state}"
             + (" (reused: same content key, not recomputed)" if seg.cached and seg.state == "done" else ""),
             "", f"{_md(status.dataset)} {_md(status.version)}; content key `{_md((seg.key or '-')[:16])}`", "",
             "| stage | state | count | seconds | completer, worker | error |", "|---|---|---|---|---|---|"]
    for name, st in seg.stages.items():
        count = "" if st.count is None else _md(f"{st.count} {st.unit or ''}".strip())
        seconds = f"{st.seconds:.2f}" if isinstance(st.seconds, (int, float)) else ""
        cached = " (cached)" if st.cached else ""
        where = " ".join(x for x in (st.completer and f"{st.completer} on {st.device or '?'}", st.worker) if x)
        lines.append(f"| {_md(name)} | {st.state}{cached} | {count} | {seconds} | {_md(where)} | "
                     f"{_md(st.error or '')} |")
    lines.append("")
    if q is None:
        lines.append("No statistics for this segment (it failed or the tables are not assembled yet).")
    else:
        def f(v, fmt):
            return fmt.format(v) if isinstance(v, (int, float)) else "-"
        refined = None if q["refined_share"] is None else 100 * q["refined_share"]
        rejected = ", ".join(f"{_md(k)} {int(v)}" for k, v in sorted(q["rejected"].items())) or "none"
        lines += ["- clips: " + f(q["clips"], "{:.0f}"), "- tracks: " + f(q["tracks"], "{:.0f}"),
                  "- speed error p50 (median over clips): " + f(q["speed_err_p50"], "{:.3g} m/s"),
                  "- refined objects: " + f(refined, "{:.0f} %"), "- rejected clips: " + rejected]
    if quality is not None and quality.gates_success is not None:
        failing = q["gates"] if q else []
        lines += ["", f"Gates: release {'passed' if quality.gates_success else 'FAILED'} "
                      f"({quality.gates_failed} of {quality.gates_total} failed); "
                      f"{len(failing)} failing gate(s) name this segment"]
        lines += [f"- **{_md(g['gate'])}** (expected {_md(g['expected'])}): {_md('; '.join(g['values']))}"
                  for g in failing]
    else:
        lines += ["", "Gates: not run yet."]
    return "\n".join(lines) + "\n"


def reused_markdown(status: ReleaseStatus) -> str:
    """The segments this run reused from completion records (never submitted, so Prefect shows no
    task run, Cached or otherwise, for them)."""
    reused = [s for s in status.segments if s.cached and s.state == "done"]
    lines = [f"# {_md(status.dataset)} {_md(status.version)}: {len(reused)} of {len(status.segments)} segments reused",
             "", "Reused segments were not submitted: their completion record with the same content key "
                 "(source checksums, configuration, code) was found in the work folder.", ""]
    if reused:
        lines += ["| split | segment | content key |", "|---|---|---|"]
        lines += [f"| {_md(s.split)} | {_md(s.segment)} | `{_md((s.key or '-')[:16])}` |" for s in reused]
    return "\n".join(lines) + "\n"


# ---- the version index (drivetrack status STORE without --version) --------------------------------

def render_index_html(dataset: str, store: str, rows: list[dict]) -> str:
    """The versions of a store, newest first: each row ``{version, created, segments_done,
    segments_failed, gates (passed/FAILED/accepted/None), bytes, files, latest, diff (text), error}``.
    Each version links to ``<version>/`` (its status page, served beside this one)."""
    e = html.escape
    body = []
    for r in rows:
        v = str(r.get("version"))
        href = safe_release_href(v)
        name = f'<a href="{e(href)}/">{e(v)}</a>' if href else e(v)
        gate = r.get("gates")
        colour = _COLOURS["done" if gate == "passed" else "failed" if gate in ("FAILED", "accepted") else "pending"]
        size = r.get("bytes")
        size_text = f"{size / 1e6:.1f} MB" if isinstance(size, (int, float)) else "-"
        body.append(
            f'<tr data-version="{e(v)}"><td class="nw"><b>{name}</b>{" (latest)" if r.get("latest") else ""}</td>'
            f'<td class="nw">{e(str(r.get("created") or "-"))}</td>'
            f'<td class="nw">{e(str(r.get("segments_done", "-")))} done, {e(str(r.get("segments_failed", "-")))} failed</td>'
            f'<td class="st" style="background:{colour[0]};color:{colour[1]}">{e(str(gate or "-"))}</td>'
            f'<td class="nw">{e(size_text)} · {e(str(r.get("files", "-")))} files</td>'
            f'<td class="small">{e(r.get("diff") or "")}</td><td class="err">{e(r.get("error") or "")}</td></tr>')
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8">
<title>{e(dataset)}: released versions</title>
<style>{_CSS}</style></head>
<body>
<h1>{e(dataset)}: released versions</h1>
<div class="meta">store <code>{e(store)}</code> · {len(rows)} versions, newest first · each links to its status page</div>
<table id="versions"><tr><th>version</th><th>created</th><th>segments</th><th>gates</th><th>size</th>
<th>change from the previous version</th><th>error</th></tr>
{"".join(body) or '<tr><td colspan="99">no published versions</td></tr>'}
</table>
</body></html>
"""
