"""Golden test: a small synthetic source annotated, gated and published gives the same files.

Issue 14 regroups the package without changing behaviour; this test is its proof. It digests every
file of the annotation output and of the published release into ``tests/golden/release.json`` and
compares. Data files (npz clips, previews) are compared by their sha256, byte for byte; the clips
and frames tables by a digest of their non-float columns (ids, frames, visibility flags: exactly)
and, per float column, its count, non-finite count, sum, sum of squares, a position-weighted sum,
minimum and maximum; statistics tables cell by cell. Floats are compared to a relative 1e-6
(``_same``): the last bits of float results differ between numpy / BLAS / numba builds (a fresh
virtual environment on 2026-11-29 changed a float32 track's last bit and a percentile's ninth
digit), which is not a change of behaviour. Files that
carry run-specific values are compared after normalisation, and only those values are masked:

- the absolute temporary paths of this run (``<out>``, ``<store>``, ``<source>``),
- wall-clock times (ISO timestamps, Great Expectations run ids, ``*seconds`` fields and timings),
- sha256 digests and byte sizes inside JSON/Markdown (also the gate binding's ``[path, bytes,
  sha256]`` entries), and the card's short gate-binding id (they
  hash the files above, which carry run-specific values themselves, such as the statistics tables'
  timing columns; the data files' own digests are compared directly),
- the code fingerprint and git commit (they change with every commit by design), random ids
  (uuid4), the folder the package is installed in (the gate config's path).

Great Expectations' Data Docs HTML is compared by file name only (its pages embed run ids).
Regenerate after an intended output change with ``DRIVETRACK_UPDATE_GOLDEN=1 pytest
tests/test_golden_release.py`` and say why in the commit.
"""
from __future__ import annotations

import hashlib
import io
import json
import math
import os
import re
import shutil
from pathlib import Path

import pyarrow.parquet as pq

from drivetrack.cli import main

GOLDEN = Path(__file__).parent / "golden" / "release.json"

_TS = re.compile(r"\d{4}-\d{2}-\d{2}T\d{2}:\d{2}:\d{2}(\.\d+)?Z?|\d{8}T\d{6}\.\d+Z")
_HEX64 = re.compile(r"\b[0-9a-f]{64}\b")
_GIT = re.compile(r"\b(git [0-9a-f]{7,40}|\+g[0-9a-f]{7,40})(\.dirty)?\b")
_BINDING = re.compile(r"(binding `)[0-9a-f]{8,64}(`)")  # the card's short binding id (hashes timed tables)
_UUID = re.compile(r"\b[0-9a-f]{8}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{12}\b")
_VOLATILE_KEY = re.compile(r"(second|timing|(^|_)size$|bytes|contentsize|^created|published|^code(_version)?$"
                           r"|fingerprint|run_id|run_time|time_utc|_utc$|^time$|duration)", re.I)
_VOLATILE_COLUMN = re.compile(r"(cpu_seconds|_seconds)$")
_BINARY = (".npz", ".png", ".jpg", ".jpeg", ".mp4", ".gif", ".webp")


def _mask_text(text: str, bases: dict[str, str]) -> str:
    for base, name in bases.items():
        text = text.replace(f"file://{base}", name).replace(base, name)
    text = _TS.sub("<time>", text)
    text = _GIT.sub("<git>", text)
    text = _BINDING.sub(r"\1<binding>\2", text)
    text = _UUID.sub("<uuid>", text)
    return _HEX64.sub("<sha256>", text)


def _mask_json(value, bases: dict[str, str], key: str = ""):
    if key == "binding" and isinstance(value, dict):
        # the gate binding: [path, bytes, sha256] per file; the files' sizes follow their bytes
        return {k: [[_mask_text(e[0], bases)] + ["<masked>"] * (len(e) - 1) if isinstance(e, list) and e else e
                    for e in v] if isinstance(v, list) else _mask_json(v, bases, k)
                for k, v in sorted(value.items())}
    if isinstance(value, dict):
        return {k: ("<masked>" if _VOLATILE_KEY.search(k) else _mask_json(v, bases, k))
                for k, v in sorted(value.items())}
    if isinstance(value, list):
        return [_mask_json(v, bases, key) for v in value]
    if isinstance(value, str):
        return _mask_text(value, bases)
    return value


#: floats in the golden document are compared to this relative tolerance (``_same``)
_REL = 1e-6


def _same(a, b) -> bool:
    """``a == b`` for golden documents, floats (not ints, not bools) to a relative ``_REL``."""
    if isinstance(a, float) and isinstance(b, float):
        return math.isclose(a, b, rel_tol=_REL, abs_tol=1e-12) or a == b
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    return type(a) is type(b) and a == b


def _float_summary(column) -> list:
    """A float column (or list-of-float column) of a data table as ``[count, non-finite, sum,
    sum of squares, position-weighted sum, min, max]`` of its finite values (float64)."""
    import numpy as np
    import pyarrow as pa
    import pyarrow.compute as pc

    values = column.combine_chunks() if isinstance(column, pa.ChunkedArray) else column
    while pa.types.is_list(values.type) or pa.types.is_large_list(values.type):
        values = pc.list_flatten(values)
    x = np.asarray(values.to_numpy(zero_copy_only=False), dtype=np.float64)
    finite = np.isfinite(x)
    v = x[finite]
    weight = (np.flatnonzero(finite) % 97 + 1) / 97.0
    return [int(x.size), int((~finite).sum()), float(v.sum()), float((v * v).sum()), float((v * weight).sum()),
            float(v.min()) if v.size else None, float(v.max()) if v.size else None]


def _is_float_column(field) -> bool:
    import pyarrow as pa

    t = field.type
    while pa.types.is_list(t) or pa.types.is_large_list(t):
        t = t.value_type
    return pa.types.is_floating(t)


def _cell(value):
    """A table cell for the golden document (NaN and inf as text; ``_same`` compares floats)."""
    if isinstance(value, float):
        return value if value == value and abs(value) != float("inf") else str(value)
    if isinstance(value, list):
        return [_cell(v) for v in value]
    if isinstance(value, dict):
        return {k: _cell(v) for k, v in value.items()}
    return value if isinstance(value, (int, str, bool, type(None))) else str(value)


def _digest_file(path: Path, rel: str, bases: dict[str, str]):
    """sha256 of a data file; the masked document of a JSON or text file (so a diff shows what changed)."""
    data = path.read_bytes()
    if rel.endswith(_BINARY):
        return hashlib.sha256(data).hexdigest()
    if rel.endswith(".html"):
        return "<html: compared by name>"
    if rel.endswith(".parquet"):
        table = pq.read_table(io.BytesIO(data))
        keep = [c for c in table.column_names if not _VOLATILE_COLUMN.search(c)]
        table = table.select(keep)
        if "stats/" not in rel:
            # data tables (clips, frames): their non-float content exactly, by digest (the parquet
            # bytes themselves may change with the pyarrow version), their float columns summarised
            exact = [f.name for f in table.schema if not _is_float_column(f)]
            doc = {"schema": [f"{f.name}:{f.type}" for f in table.schema], "rows": table.select(exact).to_pydict()}
            return {"exact": hashlib.sha256(json.dumps(doc, sort_keys=True, default=str).encode()).hexdigest(),
                    "floats": {f.name: _float_summary(table[f.name]) for f in table.schema if _is_float_column(f)}}
        # statistics tables: the table itself, so that a diff names the column that changed
        # (statistics such as residuals and percentiles differ in their last bits between
        # numpy/BLAS builds, which is not a change of behaviour: ``_same``)
        return {"schema": [f"{f.name}:{f.type}" for f in table.schema],
                "columns": {name: [_cell(v) for v in values] for name, values in table.to_pydict().items()}}
    if rel.endswith(".json"):
        return _mask_json(json.loads(data), bases)
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:  # a binary file of another kind (an icon, an image): byte for byte
        return hashlib.sha256(data).hexdigest()
    return _mask_text(text, bases).splitlines()


def _digest_tree(root: Path, bases: dict[str, str]) -> dict:
    out = {}
    for path in sorted(root.rglob("*")):
        if path.is_file():
            rel = path.relative_to(root).as_posix()
            out[_TS.sub("<time>", rel)] = _digest_file(path, rel, bases)
    return out


def test_golden_release_is_unchanged(synth_source, annotated_output, tmp_path, capsys):
    out = tmp_path / "out"
    shutil.copytree(annotated_output, out)
    store = tmp_path / "store"
    assert main(["gates", str(out)]) == 0
    assert main(["publish", str(out), "--store", str(store), "--version", "0.1.0"]) == 0
    capsys.readouterr()
    import drivetrack

    package = str(Path(drivetrack.__file__).resolve().parent)
    bases = {str(out): "<out>", str(store): "<store>", str(annotated_output): "<out>",
             str(synth_source): "<source>", package: "<package>", str(Path(package).parent): "<checkout>"}
    digest = {"out": _digest_tree(out, bases), "store": _digest_tree(store, bases)}
    if os.environ.get("DRIVETRACK_UPDATE_GOLDEN"):
        GOLDEN.parent.mkdir(exist_ok=True)
        GOLDEN.write_text(json.dumps(digest, indent=1, sort_keys=True) + "\n")
    golden = json.loads(GOLDEN.read_text())
    for tree in ("out", "store"):
        missing = sorted(set(golden[tree]) - set(digest[tree]))
        extra = sorted(set(digest[tree]) - set(golden[tree]))
        changed = sorted(k for k in set(golden[tree]) & set(digest[tree]) if not _same(golden[tree][k], digest[tree][k]))
        for k in changed[:3]:
            print(f"--- {tree}/{k}\n{json.dumps(golden[tree][k], indent=1)[:3000]}\n+++\n"
                  f"{json.dumps(digest[tree][k], indent=1)[:3000]}")
        assert not (missing or extra or changed), (
            f"{tree}: files missing {missing}, new {extra}, changed {changed} "
            f"(see the module docstring to regenerate after an intended change)")
