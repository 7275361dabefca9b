"""The gate report: per-gate results, failures with the failing objects or segments, card text, HTML.

Everything here is plain Python (no Great Expectations import): ``GateReport.to_dict()`` is what
``validation/gates.json`` holds and what ``publish_release(gate_report=...)`` receives. Non-finite
floats are written as the strings ``"NaN"``, ``"Infinity"``, ``"-Infinity"`` so that the JSON is
strict (an observed NaN is the finding, it must not disappear).
"""
from __future__ import annotations

import html
import math
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

#: Failing rows listed per gate in the report (the Great Expectations JSON keeps all of them).
MAX_FAILING_LISTED = 200


def plain(value: Any) -> Any:
    """``value`` with numpy scalars/arrays, tuples and non-finite floats turned into JSON types."""
    if isinstance(value, dict):
        return {str(k): plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple, set)):
        return [plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return [plain(v) for v in value.tolist()]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return "NaN" if math.isnan(value) else ("Infinity" if value > 0 else "-Infinity")
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    return str(value)


@dataclass
class GateResult:
    """Outcome of one gate.

    ``observed``: the aggregate GX observed value (release gates) or a summary of the unexpected
    rows; ``expected``: the bounds (``min_value``, ``max_value``, ``mostly``, ``value_set``);
    ``failing``: up to MAX_FAILING_LISTED rows, each the row's key columns plus the checked
    column values; ``num_failing``: all of them.
    """

    gate: str
    level: str
    table: str
    expectation: str
    columns: list[str]
    success: bool
    observed: Any
    expected: dict
    reason: str
    element_count: int | None = None
    num_failing: int = 0
    failing: list[dict] = field(default_factory=list)
    error: str | None = None

    def to_dict(self) -> dict:
        return plain(asdict(self))


@dataclass
class GateReport:
    """All gate results of one run on one annotation output folder."""

    success: bool
    out_dir: str
    results: list[GateResult]
    config: dict
    config_sha256: str
    gx_version: str
    created_utc: str
    tables: dict[str, str]
    seconds: float = 0.0
    #: What was validated (:mod:`drivetrack.gates.binding`): sha256 of each statistics table, the
    #: clip files (path, size, sha256) and the configuration fingerprint. Publish checks it.
    binding: dict | None = None

    @property
    def failures(self) -> list[GateResult]:
        return [r for r in self.results if not r.success]

    def summary(self) -> dict:
        by_level = {}
        for r in self.results:
            s = by_level.setdefault(r.level, {"evaluated": 0, "passed": 0, "failed": 0})
            s["evaluated"] += 1
            s["passed" if r.success else "failed"] += 1
        return by_level

    def to_dict(self) -> dict:
        return plain({
            "success": bool(self.success),
            "out_dir": self.out_dir,
            "created_utc": self.created_utc,
            "gx_version": self.gx_version,
            "config_sha256": self.config_sha256,
            "config": self.config,
            "tables": self.tables,
            "seconds": round(self.seconds, 3),
            "summary": self.summary(),
            "failures": [r.to_dict() for r in self.failures],
            "results": [r.to_dict() for r in self.results],
            "binding": self.binding,
        })


def _as_dict(report: GateReport | dict) -> dict:
    return report.to_dict() if isinstance(report, GateReport) else report


def _fmt(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


def expected_text(expected: dict) -> str:
    """``expected`` bounds as a short phrase, e.g. ``<= 0.75 for >= 99% of rows``."""
    parts = []
    lo, hi = expected.get("min_value"), expected.get("max_value")
    if lo is not None and hi is not None:
        parts.append(f"in [{_fmt(lo)}, {_fmt(hi)}]")
    elif hi is not None:
        parts.append(f"<= {_fmt(hi)}")
    elif lo is not None:
        parts.append(f">= {_fmt(lo)}")
    if "value_set" in expected:
        parts.append(f"in {expected['value_set']}")
    if expected.get("equal_to"):
        parts.append(f"== {expected['equal_to']}")
    if expected.get("greater_or_equal_to"):
        parts.append(f">= {expected['greater_or_equal_to']}")
    if expected.get("unique"):
        parts.append("unique")
    if expected.get("not_null"):
        parts.append("not null")
    if expected.get("mostly") is not None and expected["mostly"] < 1:
        parts.append(f"for >= {expected['mostly']:.0%} of rows")
    return " ".join(parts) or "-"


def failing_text(result: dict, limit: int = 10) -> str:
    """The first ``limit`` failing rows as ``segment/camera/object_id (column=value)``."""
    rows = result.get("failing") or []
    keys = [k for k in ("segment", "camera", "object_id") if rows and k in rows[0]] or \
        [k for k in ("split",) if rows and k in rows[0]]
    out = []
    for row in rows[:limit]:
        name = "/".join(str(row[k]) for k in keys)
        vals = ", ".join(f"{c}={_fmt(v)}" for c, v in row.items()
                         if c not in ("split", "segment", "camera", "object_id"))
        out.append(f"{name} ({vals})" if vals else name)
    more = result.get("num_failing", 0) - len(out)
    return "; ".join(out) + (f"; and {more} more" if more > 0 else "")


def failure_lines(report: GateReport | dict) -> list[str]:
    """One line per failed gate: gate, expectation, observed against expected, failing rows."""
    d = _as_dict(report)
    lines = []
    for f in d["failures"]:
        line = (f"FAILED {f['gate']} [{f['level']}] {f['expectation']}"
                f"({', '.join(f['columns'])}): observed {_fmt(f['observed'])}, "
                f"expected {expected_text(f['expected'])}")
        if f.get("error"):
            line += f"; error: {f['error']}"
        if f.get("failing"):
            line += f"; failing {f['num_failing']}: {failing_text(f)}"
        lines.append(line)
    return lines


def card_summary(report: GateReport | dict, accepted_reason: str | None = None) -> str:
    """Markdown section for the dataset card: verdict, per-level counts, release medians, failures.

    ``accepted_reason``: the ``--accept-failed-gates`` reason when a failing release was published
    anyway; it is stated in the card next to the failures.
    """
    d = _as_dict(report)
    ok = d["success"]
    lines = ["## Validation gates", ""]
    verdict = "**passed**" if ok else "**FAILED**"
    lines.append(f"All release gates {verdict}." if ok else f"Release gates {verdict}: "
                 f"{len(d['failures'])} of {len(d['results'])} gates failed.")
    if not ok and accepted_reason:
        lines.append(f"Published anyway with `--accept-failed-gates`: {accepted_reason}")
    lines += ["", f"Gate configuration sha256 `{d['config_sha256'][:16]}`, Great Expectations "
              f"{d['gx_version']}, run {d['created_utc']}. Full report: `validation/report.html`, "
              "`validation/gates.json`, Data Docs in `validation/data_docs/`.", "",
              "| level | gates | passed | failed |", "|---|---|---|---|"]
    for level, s in d["summary"].items():
        lines.append(f"| {level} | {s['evaluated']} | {s['passed']} | {s['failed']} |")
    medians = [r for r in d["results"] if r["gate"].startswith("release.speed_err_median.")]
    if medians:
        paper = d["config"].get("paper_speed_err_median_mps", {})
        lines += ["", "Track speed against annotated box speed (median over objects of each "
                  "per-object percentile of |track speed - box speed|, m/s):", "",
                  "| percentile | this release | bound | paper (NN) |", "|---|---|---|---|"]
        for r in medians:
            p = r["gate"].rsplit(".", 1)[1]
            lines.append(f"| {p} | {_fmt(r['observed'])} | <= {_fmt(r['expected'].get('max_value'))}"
                         f" | {_fmt(paper.get(p, '-'))} |")
    if d["failures"]:
        lines += ["", "Failed gates:", ""]
        lines += [f"- {line[len('FAILED '):]}" for line in failure_lines(d)]
    return "\n".join(lines) + "\n"


_CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Helvetica,Arial,sans-serif;margin:2em;color:#222}
table{border-collapse:collapse;margin:1em 0;font-size:14px}
th,td{border:1px solid #ccc;padding:4px 8px;text-align:left;vertical-align:top}
th{background:#f0f0f0}.pass{color:#1a7f37;font-weight:bold}.fail{color:#c62828;font-weight:bold}
tr.failrow{background:#fff1f1}code{background:#f5f5f5;padding:0 3px}
.small{font-size:12px;color:#555}
"""


def report_html(report: GateReport | dict) -> str:
    """A self-contained HTML page (inline CSS, no script, no external resource)."""
    d = _as_dict(report)
    e = lambda x: html.escape(_fmt(x))  # noqa: E731
    verdict = '<span class="pass">PASSED</span>' if d["success"] else '<span class="fail">FAILED</span>'
    out = ["<!DOCTYPE html><html><head><meta charset='utf-8'><title>DriveTrack release gates</title>",
           f"<style>{_CSS}</style></head><body>",
           f"<h1>DriveTrack release gates: {verdict}</h1>",
           f"<p>Output folder <code>{e(d['out_dir'])}</code>; run {e(d['created_utc'])}; "
           f"Great Expectations {e(d['gx_version'])}; configuration sha256 "
           f"<code>{e(d['config_sha256'])}</code> ({e(d['config'].get('source', {}))}).</p>",
           "<table><tr><th>level</th><th>gates</th><th>passed</th><th>failed</th></tr>"]
    for level, s in d["summary"].items():
        out.append(f"<tr><td>{e(level)}</td><td>{s['evaluated']}</td><td>{s['passed']}</td>"
                   f"<td>{s['failed']}</td></tr>")
    out.append("</table>")
    if d["failures"]:
        out.append("<h2>Failures</h2>")
        for f in d["failures"]:
            out.append(f"<h3 class='fail'>{e(f['gate'])} [{e(f['level'])}]</h3>"
                       f"<p><code>{e(f['expectation'])}</code> on <code>{e(f['table'])}"
                       f".{e(', '.join(f['columns']))}</code>: observed {e(f['observed'])}, "
                       f"expected {e(expected_text(f['expected']))}"
                       + (f"; error: {e(f['error'])}" if f.get("error") else "")
                       + f"</p><p class='small'>Why: {e(f['reason'])}</p>")
            if f.get("failing"):
                cols = list(f["failing"][0])
                out.append(f"<p>{f['num_failing']} failing row(s)"
                           + (f", first {len(f['failing'])} listed" if f["num_failing"] > len(f["failing"]) else "")
                           + ":</p><table><tr>" + "".join(f"<th>{e(c)}</th>" for c in cols) + "</tr>")
                for row in f["failing"]:
                    out.append("<tr>" + "".join(f"<td>{e(row.get(c))}</td>" for c in cols) + "</tr>")
                out.append("</table>")
    out.append("<h2>All gates</h2><table><tr><th>gate</th><th>level</th><th>result</th>"
               "<th>expectation</th><th>observed</th><th>expected</th><th>reason</th></tr>")
    for r in d["results"]:
        status = '<span class="pass">pass</span>' if r["success"] else '<span class="fail">FAIL</span>'
        out.append(f"<tr class='{'' if r['success'] else 'failrow'}'><td>{e(r['gate'])}</td>"
                   f"<td>{e(r['level'])}</td><td>{status}</td>"
                   f"<td><code>{e(r['expectation'])}</code><br>{e(', '.join(r['columns']))}</td>"
                   f"<td>{e(r['observed'])}</td><td>{e(expected_text(r['expected']))}</td>"
                   f"<td class='small'>{e(r['reason'])}</td></tr>")
    out.append("</table><p class='small'>Great Expectations Data Docs: "
               "<a href='data_docs/index.html'>data_docs/index.html</a>; machine-readable: "
               "<a href='gates.json'>gates.json</a>.</p></body></html>")
    return "\n".join(out)
