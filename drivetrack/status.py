"""Per-segment, per-stage status of a release build: the model, ``status.json`` and a
self-contained ``status.html`` (inline CSS, no scripts, no network), pure core (no Prefect).

The release flow (``flows/release.py``) owns one :class:`ReleaseStatus`, updates it as jobs
finish, mirrors it to Prefect artifacts and writes both files into the annotation folder, so
that they are published inside the release and served by ``drivetrack status STORE``.

States: ``pending`` (not started), ``running``, ``done``, ``failed`` (with its error), and
``skipped`` (not run because an earlier stage of the same segment failed). A ``done`` stage may
be ``cached``: its content-keyed result of an earlier run was reused.
"""
from __future__ import annotations

import html
import json
import time
from dataclasses import asdict, dataclass, field
from datetime import datetime, timezone

import fsspec

__all__ = ["STATES", "SEGMENT_STAGES", "RELEASE_STAGES", "StageStatus", "SegmentStatus", "ReleaseStatus",
           "render_status_html", "write_status", "read_status", "read_release_status", "StatusError",
           "STATUS_JSON", "STATUS_HTML"]

STATES = ("pending", "running", "done", "failed", "skipped")
SEGMENT_STAGES = ("ingest", "depth", "tracks", "write")
"""Per segment: read and validate the source, depth completion (GPU queue), per-object track
jobs, writing the clip files and the segment's tables."""
RELEASE_STAGES = ("list", "segments", "statistics", "previews", "gates", "publish")
"""Once per release: list segments, all segment jobs, merged statistics, gates, publish."""
STATUS_JSON = "status.json"
STATUS_HTML = "status.html"
FORMAT = "drivetrack-status/1"

_COLOURS = {  # state -> (background, text)
    "pending": ("#e9ecef", "#495057"),
    "running": ("#cfe2ff", "#084298"),
    "done": ("#d1e7dd", "#0f5132"),
    "failed": ("#f8d7da", "#842029"),
    "skipped": ("#fff3cd", "#664d03"),
}


class StatusError(ValueError):
    """A status document or state that does not follow the format; the message names it."""


def _check_state(state: str, where: str) -> str:
    if state not in STATES:
        raise StatusError(f"{where}: unknown state {state!r}; expected one of {', '.join(STATES)}")
    return state


def _utc(t: float | None) -> str | None:
    if t is None:
        return None
    return datetime.fromtimestamp(t, timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")


@dataclass
class StageStatus:
    """One stage of one segment (or of the release). Times are unix seconds; ``seconds`` is the
    stage's own duration (``finished - started`` unless the job reported it); ``count`` counts
    what the stage produced, in ``unit`` (frames, depth batches, objects, files)."""
    state: str = "pending"
    started: float | None = None
    finished: float | None = None
    seconds: float | None = None
    count: int | None = None
    unit: str | None = None
    error: str | None = None
    cached: bool = False
    worker: str | None = None

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict, where: str = "stage") -> "StageStatus":
        if not isinstance(d, dict):
            raise StatusError(f"{where}: expected an object, found {type(d).__name__}")
        unknown = set(d) - set(cls.__dataclass_fields__)
        if unknown:
            raise StatusError(f"{where}: unknown fields {sorted(unknown)}")
        s = cls(**d)
        _check_state(s.state, where)
        return s


@dataclass
class SegmentStatus:
    split: str
    segment: str
    key: str | None = None
    stages: dict[str, StageStatus] = field(default_factory=lambda: {s: StageStatus() for s in SEGMENT_STAGES})

    @property
    def state(self) -> str:
        """failed if any stage failed; done if all are done; pending if none started; else running."""
        states = [s.state for s in self.stages.values()]
        if "failed" in states:
            return "failed"
        if all(s == "done" for s in states):
            return "done"
        if all(s == "pending" for s in states):
            return "pending"
        return "running"

    @property
    def error(self) -> str | None:
        for name, s in self.stages.items():
            if s.error:
                return f"{name}: {s.error}"
        return None

    @property
    def cached(self) -> bool:
        return all(s.cached for s in self.stages.values())

    @property
    def seconds(self) -> float:
        return float(sum(s.seconds or 0.0 for s in self.stages.values()))

    def to_dict(self) -> dict:
        return {"split": self.split, "segment": self.segment, "key": self.key, "state": self.state,
                "error": self.error, "cached": self.cached,
                "stages": {k: v.to_dict() for k, v in self.stages.items()}}

    @classmethod
    def from_dict(cls, d: dict, where: str = "segment") -> "SegmentStatus":
        try:
            split, segment = d["split"], d["segment"]
        except (KeyError, TypeError) as e:
            raise StatusError(f"{where}: missing field {e}") from None
        where = f"{where} {split}/{segment}"
        stages = {k: StageStatus.from_dict(v, f"{where} stage {k}") for k, v in (d.get("stages") or {}).items()}
        return cls(split=split, segment=segment, key=d.get("key"), stages=stages)


@dataclass
class ReleaseStatus:
    """Everything the dashboard shows. Mutate through :meth:`update` / :meth:`update_release`
    so that ``updated`` moves and unknown segments, stages or states are refused."""
    dataset: str
    version: str
    source: str | None = None
    store: str | None = None
    created: float = field(default_factory=time.time)
    updated: float = field(default_factory=time.time)
    fingerprint: str | None = None
    published: bool = False
    message: str | None = None
    stages: dict[str, StageStatus] = field(default_factory=lambda: {s: StageStatus() for s in RELEASE_STAGES})
    segments: list[SegmentStatus] = field(default_factory=list)
    previews: list[str] = field(default_factory=list)   # release-relative paths (drivetrack show)

    # ---- mutation -----------------------------------------------------------------------
    def add_segment(self, split: str, segment: str, key: str | None = None) -> SegmentStatus:
        if self.find(split, segment) is not None:
            raise StatusError(f"segment {split}/{segment} is already in the status of {self.version}")
        s = SegmentStatus(split=split, segment=segment, key=key)
        self.segments.append(s)
        self.updated = time.time()
        return s

    def find(self, split: str, segment: str) -> SegmentStatus | None:
        for s in self.segments:
            if s.split == split and s.segment == segment:
                return s
        return None

    def update(self, split: str, segment: str, stage: str, state: str, **fields) -> StageStatus:
        """Set one segment stage's state and fields; ``running`` stamps ``started``, ``done`` and
        ``failed`` stamp ``finished`` and ``seconds`` unless given."""
        seg = self.find(split, segment)
        if seg is None:
            raise StatusError(f"no segment {split}/{segment} in the status of {self.version}")
        if stage not in seg.stages:
            raise StatusError(f"segment {split}/{segment}: unknown stage {stage!r}; expected one of "
                              f"{', '.join(seg.stages)}")
        return self._set(seg.stages[stage], state, f"segment {split}/{segment} stage {stage}", fields)

    def update_release(self, stage: str, state: str, **fields) -> StageStatus:
        if stage not in self.stages:
            raise StatusError(f"unknown release stage {stage!r}; expected one of {', '.join(self.stages)}")
        return self._set(self.stages[stage], state, f"release stage {stage}", fields)

    def _set(self, st: StageStatus, state: str, where: str, fields: dict) -> StageStatus:
        _check_state(state, where)
        unknown = set(fields) - set(StageStatus.__dataclass_fields__)
        if unknown:
            raise StatusError(f"{where}: unknown fields {sorted(unknown)}")
        now = time.time()
        st.state = state
        for k, v in fields.items():
            setattr(st, k, v)
        if state == "running" and "started" not in fields:
            st.started = now
        if state in ("done", "failed") and "finished" not in fields:
            st.finished = now
        if state in ("done", "failed") and "seconds" not in fields and st.started is not None:
            st.seconds = max(0.0, (st.finished or now) - st.started)
        if state == "pending":
            st.started = st.finished = st.seconds = None
        self.updated = now
        return st

    # ---- summaries ----------------------------------------------------------------------
    def counts(self) -> dict[str, int]:
        """Segments per state (every state present, zero included)."""
        out = {s: 0 for s in STATES}
        for seg in self.segments:
            out[seg.state] += 1
        return out

    def stage_counts(self) -> dict[str, dict[str, int]]:
        """Per segment stage: segments per state."""
        out = {name: {s: 0 for s in STATES} for name in SEGMENT_STAGES}
        for seg in self.segments:
            for name, st in seg.stages.items():
                out.setdefault(name, {s: 0 for s in STATES})[st.state] += 1
        return out

    @property
    def state(self) -> str:
        states = [s.state for s in self.stages.values()]
        if "failed" in states:
            return "failed"
        if all(s in ("done", "skipped") for s in states):
            return "done"
        if all(s == "pending" for s in states):
            return "pending"
        return "running"

    def table_rows(self) -> list[dict]:
        """One flat row per segment (the Prefect table artifact)."""
        rows = []
        for seg in self.segments:
            row = {"split": seg.split, "segment": seg.segment, "state": seg.state,
                   "cached": seg.cached, "seconds": round(seg.seconds, 2)}
            for name, st in seg.stages.items():
                row[name] = st.state + (f" {st.count} {st.unit or ''}".rstrip() if st.count is not None else "")
            row["error"] = seg.error or ""
            rows.append(row)
        return rows

    def to_dict(self) -> dict:
        return {"format": FORMAT, "dataset": self.dataset, "version": self.version, "source": self.source,
                "store": self.store, "created": self.created, "created_utc": _utc(self.created),
                "updated": self.updated, "updated_utc": _utc(self.updated), "fingerprint": self.fingerprint,
                "published": self.published, "message": self.message, "state": self.state,
                "counts": self.counts(), "stage_counts": self.stage_counts(),
                "stages": {k: v.to_dict() for k, v in self.stages.items()},
                "segments": [s.to_dict() for s in self.segments], "previews": list(self.previews)}

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=1, allow_nan=False)

    @classmethod
    def from_dict(cls, d: dict, where: str = "status.json") -> "ReleaseStatus":
        if not isinstance(d, dict):
            raise StatusError(f"{where}: expected a JSON object, found {type(d).__name__}")
        if d.get("format") != FORMAT:
            raise StatusError(f"{where}: format {d.get('format')!r}, expected {FORMAT!r}")
        for k in ("dataset", "version"):
            if not isinstance(d.get(k), str):
                raise StatusError(f"{where}: field {k!r} must be a string, found {d.get(k)!r}")
        return cls(dataset=d["dataset"], version=d["version"], source=d.get("source"), store=d.get("store"),
                   created=d.get("created") or 0.0, updated=d.get("updated") or 0.0,
                   fingerprint=d.get("fingerprint"), published=bool(d.get("published")),
                   message=d.get("message"),
                   stages={k: StageStatus.from_dict(v, f"{where}: release stage {k}")
                           for k, v in (d.get("stages") or {}).items()},
                   segments=[SegmentStatus.from_dict(s, f"{where}: segment") for s in d.get("segments") or []],
                   previews=[str(p) for p in d.get("previews") or []])


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
.small{font-size:11px;opacity:.85}
.err{font-family:ui-monospace,Menlo,Consolas,monospace;font-size:12px;color:#842029;white-space:pre-wrap;word-break:break-word}
.legend span{display:inline-block;padding:2px 8px;border-radius:3px;margin-right:6px;font-size:12px}
h2{font-size:16px;margin:22px 0 8px}
"""


def _cell(st: StageStatus) -> str:
    bg, fg = _COLOURS[st.state]
    bits = [f"<b>{html.escape(st.state)}</b>"]
    if st.cached:
        bits.append("cached")
    details = []
    if st.count is not None:
        details.append(f"{st.count} {html.escape(st.unit or '')}".rstrip())
    if st.seconds is not None:
        details.append(f"{st.seconds:.2f} s")
    if st.worker:
        details.append(html.escape(st.worker))
    inner = " ".join(bits) + (f'<div class="small">{" · ".join(details)}</div>' if details else "")
    title = f' title="{html.escape(st.error)}"' if st.error else ""
    return f'<td class="st" data-state="{st.state}" style="background:{bg};color:{fg}"{title}>{inner}</td>'


def _previews_html(previews: list[str]) -> str:
    """Links to the release's previews (paths relative to the release folder the page sits in)."""
    if not previews:
        return ""
    e = html.escape
    items = "".join(f'<a href="{e(p)}"><img src="{e(p)}" alt="{e(p)}" style="max-width:420px;margin:4px"></a>'
                    if p.endswith(".png") else f'<p><a href="{e(p)}">clip: {e(p)}</a></p>' for p in previews)
    return f"<h2>Previews</h2>\n<div>{items}</div>"


def render_status_html(status: ReleaseStatus, *, refresh_s: int | None = None) -> str:
    """A self-contained HTML page: summary counts, release stages, one row per segment with one
    coloured cell per stage (state, count, duration, worker) and the error. ``refresh_s`` adds a
    meta refresh, for a page watched while the build runs."""
    e = html.escape
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
            f'<td class="err">{e(seg.error or "")}</td></tr>')
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
<table id="segments"><tr><th>split</th><th>segment</th><th>state</th><th>time</th>{seg_head}<th>error</th></tr>
{"".join(rows) or '<tr><td colspan="99">no segments</td></tr>'}
</table>
<p class="legend">{legend}</p>
{_previews_html(status.previews)}
</body></html>
"""


# ---- files -------------------------------------------------------------------------------------

def write_status(out_url: str, status: ReleaseStatus, *, storage_options: dict | None = None,
                 refresh_s: int | None = None) -> tuple[str, str]:
    """Write ``status.json`` and ``status.html`` into the folder ``out_url`` (any fsspec URL),
    each through a temporary name then a move, so that a reader never sees half a file.
    Returns both URLs."""
    fs, root = fsspec.core.url_to_fs(str(out_url), **(storage_options or {}))
    root = root.rstrip("/")
    fs.makedirs(root, exist_ok=True)
    out = []
    for name, text in ((STATUS_JSON, status.to_json()), (STATUS_HTML, render_status_html(status, refresh_s=refresh_s))):
        path, tmp = f"{root}/{name}", f"{root}/.{name}.tmp"
        with fs.open(tmp, "w", encoding="utf-8") as f:
            f.write(text)
        fs.mv(tmp, path)
        out.append(path)
    return out[0], out[1]


def read_status(url: str, *, storage_options: dict | None = None) -> ReleaseStatus:
    """Read a ``status.json`` (file URL, or a folder holding one)."""
    fs, path = fsspec.core.url_to_fs(str(url), **(storage_options or {}))
    if fs.isdir(path):
        path = f"{path.rstrip('/')}/{STATUS_JSON}"
    try:
        with fs.open(path, "r", encoding="utf-8") as f:
            doc = json.load(f)
    except FileNotFoundError:
        raise FileNotFoundError(f"no {STATUS_JSON} at {url}") from None
    except json.JSONDecodeError as e:
        raise StatusError(f"{path}: not valid JSON ({e})") from e
    return ReleaseStatus.from_dict(doc, where=str(path))


def read_release_status(store_url: str, version: str = "latest", dataset: str = "drivetrack-waymo", *,
                        storage_options: dict | None = None) -> tuple[str, bytes, ReleaseStatus]:
    """Resolve ``version`` (``latest`` allowed) in a release store and return
    ``(version, status.html bytes, status)``. Raises ``VersionNotFoundError`` for an unknown
    version and FileNotFoundError naming the path when the release holds no status page."""
    from drivetrack.release import open_store
    from drivetrack.release.catalog import resolve_version
    from drivetrack.release.manifest import check_version

    store = open_store(store_url, storage_options)
    v = resolve_version(store, dataset, version)
    check_version(v)
    if not store.exists(f"{dataset}/{v}/manifest.json"):
        from drivetrack.release import VersionNotFoundError
        raise VersionNotFoundError(f"{store.url_of(f'{dataset}/{v}')} is not published (no manifest.json)")
    rel_html, rel_json = f"{dataset}/{v}/{STATUS_HTML}", f"{dataset}/{v}/{STATUS_JSON}"
    for rel in (rel_html, rel_json):
        if not store.exists(rel):
            raise FileNotFoundError(f"{store.url_of(rel)} does not exist: release {v} was not built by the "
                                    f"release flow (no status page)")
    doc = json.loads(store.read_bytes(rel_json))
    return v, store.read_bytes(rel_html), ReleaseStatus.from_dict(doc, where=store.url_of(rel_json))
