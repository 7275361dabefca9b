"""Run the gates with Great Expectations and write ``OUT/validation/``.

``run_gates(out_dir, config)`` reads the statistics tables, builds one GX suite per (level, table)
from the configuration, validates them in an ephemeral context and writes:

  OUT/validation/gates.json            GateReport.to_dict(): verdict, failures, every gate, and the
                                       binding to the content validated (drivetrack.gates.binding:
                                       sha256 of the tables and of every clip file, config sha256)
  OUT/validation/report.html           self-contained page (inline CSS, no script, no network)
  OUT/validation/gx_results/<suite>.json   the raw GX validation results (JSON-safe)
  OUT/validation/data_docs/index.html  GX Data Docs, made to render offline (CDN links removed,
                                       inline CSS, a plain list of pages on the index)

Great Expectations is imported here only, inside :func:`run_gates` (about 5 s).
"""
from __future__ import annotations

import html
import json
import logging
import os
import posixpath
import re
import shutil
import tempfile
import time
from datetime import datetime, timezone
from pathlib import Path

import fsspec
from fsspec.implementations.local import LocalFileSystem
import pandas as pd

from drivetrack.gates.binding import folder_clips, make_binding
from drivetrack.gates.config import config_sha256, load_gate_config
from drivetrack.gates.report import (MAX_FAILING_LISTED, GateReport, GateResult, plain,
                                     report_html)
from drivetrack.gates.suites import GateSpec, build_specs
from drivetrack.gates.tables import GateTables, read_gate_tables

DOCS_SITE = "drivetrack_gates"  # the ephemeral context already has a 'local_site'
#: Folder of the gate artefacts inside OUT (shared with the Waymo 'validation' split's files).
VALIDATION_DIR = "validation"
#: The entries run_gates owns inside OUT/validation/ (and replaces on every run).
GATE_ARTEFACTS = ("gates.json", "report.html", "gx_results", "data_docs")


def _import_gx():
    os.environ.setdefault("GX_ANALYTICS_ENABLED", "false")
    import great_expectations as gx
    import great_expectations.expectations as gxe

    for name in ("great_expectations", "great_expectations.core", "great_expectations.data_context"):
        logging.getLogger(name).setLevel(logging.ERROR)
    return gx, gxe


def _expected(spec: GateSpec) -> dict:
    kw = spec.kwargs
    exp = {k: kw[k] for k in ("min_value", "max_value", "mostly", "value_set") if k in kw}
    if spec.expectation == "ExpectColumnPairValuesToBeEqual":
        exp["equal_to"] = kw["column_B"]
    elif spec.expectation == "ExpectColumnPairValuesAToBeGreaterThanB":
        exp["greater_or_equal_to"] = kw["column_B"]
    elif spec.expectation in ("ExpectCompoundColumnsToBeUnique", "ExpectColumnValuesToBeUnique"):
        exp["unique"] = True
    elif spec.expectation == "ExpectColumnValuesToNotBeNull":
        exp["not_null"] = True
    return exp


def _columns(spec: GateSpec) -> list[str]:
    kw = spec.kwargs
    if "column" in kw:
        return [kw["column"]]
    if "column_A" in kw:
        return [kw["column_A"], kw["column_B"]]
    return list(kw.get("column_list", []))


def _aggregate_offenders(spec: GateSpec, frame: pd.DataFrame) -> tuple[int, list[dict]]:
    """Rows beyond an aggregate bound (e.g. objects above the release median bound), worst first."""
    col = spec.kwargs.get("column")
    if spec.expectation != "ExpectColumnMedianToBeBetween" or col not in frame:
        return 0, []
    values = pd.to_numeric(frame[col], errors="coerce")
    lo, hi = spec.kwargs.get("min_value"), spec.kwargs.get("max_value")
    bad = values.isna()
    if hi is not None:
        bad |= values > hi
    if lo is not None:
        bad |= values < lo
    rows = frame.loc[bad, [*spec.keys, col]].assign(_v=values[bad].fillna(float("inf")))
    rows = rows.sort_values("_v", ascending=False).drop(columns="_v")
    return int(bad.sum()), rows.head(MAX_FAILING_LISTED).to_dict("records")


def _gate_result(spec: GateSpec, gx_result, frame: pd.DataFrame) -> GateResult:
    res = gx_result.result or {}
    exc = gx_result.exception_info or {}
    error = None
    if isinstance(exc, dict) and exc.get("raised_exception"):
        error = str(exc.get("exception_message"))
    success = bool(gx_result.success) and error is None
    element_count = res.get("element_count")
    if "observed_value" in res:
        observed = res["observed_value"]
        num_failing, failing = _aggregate_offenders(spec, frame)
        if spec.expectation == "ExpectColumnDistinctValuesToContainSet":
            missing = sorted(set(spec.kwargs["value_set"]) - set(observed or []))
            num_failing, failing = len(missing), [{"split": s} for s in missing]
    elif "unexpected_count" in res:
        n = int(res["unexpected_count"])
        observed = (f"{n} of {element_count} rows fail"
                    + (f" ({res.get('unexpected_percent', 0):.3g}%)" if n else ""))
        rows = res.get("unexpected_index_list") or []
        num_failing = n
        failing = [dict(r) for r in rows[:MAX_FAILING_LISTED] if isinstance(r, dict)]
    else:
        observed, num_failing, failing = None, 0, []
    keys = [k for k in spec.keys if k in frame.columns]
    shown = set(failing[0]) if failing else set()
    context = [c for c in spec.context if c in frame.columns and c not in shown]
    if failing and context and all(k in shown for k in keys):
        extra = frame[keys + context].drop_duplicates(keys)
        failing = pd.DataFrame(failing).merge(extra, on=keys, how="left").to_dict("records")
    if error is not None:
        observed = observed if observed is not None else "error"
    return GateResult(gate=spec.gate, level=spec.level, table=spec.table,
                      expectation=spec.expectation, columns=_columns(spec), success=success,
                      observed=plain(observed), expected=plain(_expected(spec)), reason=spec.reason,
                      element_count=None if element_count is None else int(element_count),
                      num_failing=num_failing, failing=plain(failing), error=error)


_EXTERNAL_TAG = re.compile(
    r"<link[^>]*href=\"https?://[^\"]*\"[^>]*>|<script[^>]*src=\"https?://[^\"]*\"[^>]*>\s*</script>",
    re.S)
_EXTERNAL_IMG = re.compile(r"src=\"https?://[^\"]*logo-long\.png[^\"]*\"")
_KEEP_IMAGES = {"favicon.ico", "logo-long.png"}
_OFFLINE_CSS = """<style>
body{font-family:system-ui,Helvetica,Arial,sans-serif;margin:0 1em;color:#222}
table{border-collapse:collapse;margin:.5em 0}td,th{border:1px solid #ccc;padding:3px 6px;vertical-align:top}
.table-sm td,.table-sm th{font-size:13px}.d-none{display:none}
nav .breadcrumb{list-style:none;display:flex;gap:.5em;padding:0}.text-danger{color:#c62828}.text-success{color:#1a7f37}
.card{border:1px solid #ddd;margin:.5em 0;padding:.5em}.alert{padding:.5em;border:1px solid #ccc}
.fa-check-circle::before{content:"\\2714 pass";font-style:normal;font-weight:bold}
.fa-times::before{content:"\\2718 FAIL";font-style:normal;font-weight:bold}
</style>"""


def _make_offline(docs: Path, pages: list[tuple[str, str]]) -> None:
    """Strip CDN stylesheets/scripts from the GX pages, inline a small stylesheet, list the pages
    on the index in plain HTML (the GX index table is filled by a CDN script), and drop static
    files no page references."""
    for page in docs.rglob("*.html"):
        text = page.read_text()
        text = _EXTERNAL_TAG.sub("", text)
        logo = os.path.relpath(docs / "static" / "images" / "logo-long.png", page.parent)
        text = _EXTERNAL_IMG.sub(f'src="{logo}"', text)
        text = text.replace("<head>", "<head>\n" + _OFFLINE_CSS, 1)
        if page == docs / "index.html":
            items = "".join(f'<li><a href="{html.escape(p)}">{html.escape(p)}</a> {html.escape(label)}</li>'
                            for p, label in pages)
            text = re.sub(r"<body[^>]*>", lambda m: m.group(0) + (
                "\n<div id='drivetrack-offline-index'><h2>Validation results and suites</h2><ul>"
                f"{items}</ul><p><a href='../report.html'>DriveTrack gate report</a></p></div>"), text, 1)
        page.write_text(text)
    # GX copies 4 MB of fonts and animated tutorial images; the pages use two of the images.
    shutil.rmtree(docs / "static" / "fonts", ignore_errors=True)
    images = docs / "static" / "images"
    for f in list(images.iterdir()) if images.is_dir() else []:
        if f.name not in _KEEP_IMAGES:
            f.unlink()


def _validate(specs: list[GateSpec], tables: GateTables, docs_dir: Path, results_dir: Path,
              data_docs: bool = True, progress=None):
    gx, gxe = _import_gx()
    from great_expectations.core.run_identifier import RunIdentifier
    from great_expectations.data_context.types.base import ProgressBarsConfig
    from great_expectations.data_context.types.resource_identifiers import (
        ExpectationSuiteIdentifier, ValidationResultIdentifier)

    ctx = gx.get_context(mode="ephemeral")
    ctx.variables.progress_bars = ProgressBarsConfig(globally=False)
    ctx.add_data_docs_site(DOCS_SITE, {
        "class_name": "SiteBuilder", "show_how_to_buttons": False,
        "store_backend": {"class_name": "TupleFilesystemStoreBackend",
                          "base_directory": str(docs_dir)},
        "site_index_builder": {"class_name": "DefaultSiteIndexBuilder"}})
    source = ctx.data_sources.add_or_update_pandas("drivetrack_stats")
    frames = {"objects": tables.objects, "segments": tables.segments, "splits": tables.splits}
    run_id = RunIdentifier(run_name="drivetrack_gates", run_time=datetime.now(timezone.utc))
    by_suite: dict[str, list[GateSpec]] = {}
    for spec in specs:
        by_suite.setdefault(spec.suite, []).append(spec)
    results: list[GateResult] = []
    suite_ok: dict[str, bool] = {}
    emit = progress or (lambda event, info: None)
    emit("planned", {"steps": len(by_suite) + (1 if data_docs else 0)})
    for suite_name, suite_specs in by_suite.items():
        table = suite_specs[0].table
        frame = frames[table]
        suite = gx.ExpectationSuite(name=suite_name)
        for spec in suite_specs:
            cls = getattr(gxe, spec.expectation)
            suite.add_expectation(cls(**spec.kwargs, meta={"gate": spec.gate, "level": spec.level,
                                                           "reason": spec.reason}))
        suite = ctx.suites.add(suite)
        batch = (source.add_dataframe_asset(suite_name)
                 .add_batch_definition_whole_dataframe("all")
                 .get_batch(batch_parameters={"dataframe": frame}))
        keys = [k for k in suite_specs[0].keys if k in frame.columns]
        validation = batch.validate(suite, result_format={
            "result_format": "COMPLETE", "unexpected_index_column_names": keys})
        for r in validation.results:  # GX returns numpy.bool for some expectations (STACK.md)
            r.success = bool(r.success)
        validation.success = bool(validation.success)
        validation.meta["run_id"] = run_id  # shown as run name/time in Data Docs
        suite_ok[suite_name] = validation.success
        spec_of = {s.gate: s for s in suite_specs}
        for r in validation.results:
            results.append(_gate_result(spec_of[r.expectation_config.meta["gate"]], r, frame))
        (results_dir / f"{suite_name}.json").write_text(
            json.dumps(plain(validation.to_json_dict()), indent=1, allow_nan=False))
        key = ValidationResultIdentifier(
            expectation_suite_identifier=ExpectationSuiteIdentifier(name=suite_name),
            run_id=run_id, batch_identifier=suite_name)
        ctx.validation_results_store.set(key, validation)
        emit("validated", {"suite": suite_name, "success": validation.success})
    if data_docs:
        ctx.build_data_docs(site_names=[DOCS_SITE])
        pages = []
        for page in sorted(docs_dir.rglob("*.html")):
            rel = page.relative_to(docs_dir).as_posix()
            if rel.startswith("validations/"):
                pages.append((rel, "(passed)" if suite_ok[page.stem] else "(FAILED)"))
            elif rel != "index.html":
                pages.append((rel, "(expectation suite)"))
        _make_offline(docs_dir, pages)
        emit("data_docs", {"pages": len(pages)})
    order = {s.gate: i for i, s in enumerate(specs)}
    results.sort(key=lambda r: order[r.gate])
    return results, gx.__version__


def _publish_dir(staged: Path, out_dir: str) -> None:
    """Replace the gate artefacts in ``OUT/validation/`` by the staged ones (local or fsspec URL).

    Only our own entries (GATE_ARTEFACTS) are replaced: ``OUT/validation/`` is also the folder of
    the Waymo ``validation`` split, whose track files must survive a gate run.
    """
    fs, root = fsspec.core.url_to_fs(out_dir)
    dest = posixpath.join(root.rstrip("/"), VALIDATION_DIR)
    fs.makedirs(dest, exist_ok=True)
    for name in GATE_ARTEFACTS:
        target = posixpath.join(dest, name)
        if fs.exists(target):
            fs.rm(target, recursive=True)
        src = staged / name
        if not src.exists():
            continue
        if isinstance(fs, LocalFileSystem):
            (shutil.copytree if src.is_dir() else shutil.copy2)(src, target)
        else:
            fs.put(str(src), target, recursive=src.is_dir())


def run_gates(out_dir: str, config: str | dict | None = None, *,
              data_docs: bool = True, progress=None) -> GateReport:
    """Validate the statistics of the annotation output folder ``out_dir`` against the gates.

    ``config``: None (``infra/gates.yaml``), a YAML path or a dict merged over the defaults.
    ``data_docs=False`` skips the GX Data Docs (about 2 s), for quick local checks only.
    ``progress(event, info)``: ``planned`` ({"steps"}), then ``validated`` ({"suite", "success"})
    per expectation suite and ``data_docs`` ({"pages"}) once; for progress display.
    Writes ``out_dir/validation/`` (see module docstring) and returns the :class:`GateReport`;
    ``report.success`` is False when any gate failed. Raises ``GateConfigError`` for a bad
    configuration and ``GateInputError`` for missing tables or columns.
    """
    t0 = time.perf_counter()
    cfg = load_gate_config(config)
    tables = read_gate_tables(out_dir, cfg)
    specs = build_specs(cfg, tables)
    fs, root = fsspec.core.url_to_fs(str(out_dir))
    binding = make_binding(tables.sha256, folder_clips(fs, root), config_sha256(cfg))
    with tempfile.TemporaryDirectory(prefix="drivetrack-gates-") as tmp:
        staged = Path(tmp) / "validation"
        (staged / "gx_results").mkdir(parents=True)
        results, gx_version = _validate(specs, tables, staged / "data_docs", staged / "gx_results",
                                        data_docs, progress)
        report = GateReport(
            success=all(r.success for r in results), out_dir=str(out_dir), results=results,
            config=cfg, config_sha256=config_sha256(cfg), gx_version=gx_version,
            created_utc=datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
            tables=tables.files, binding=binding)
        report.seconds = time.perf_counter() - t0
        (staged / "gates.json").write_text(json.dumps(report.to_dict(), indent=1, allow_nan=False))
        (staged / "report.html").write_text(report_html(report))
        _publish_dir(staged, out_dir)
    return report
