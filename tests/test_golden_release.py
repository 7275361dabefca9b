"""Golden test: a small synthetic source annotated, gated and published gives the same files.

Issue 14 regroups the package without changing behaviour; this test is its proof. It digests every
file of the annotation output and of the published release into ``tests/golden/release.json`` and
compares. Data files (npz clips, previews) are compared by their sha256, byte for byte; the clips
and frames tables by a digest of their content; statistics tables cell by cell (floats to 9
significant digits, see ``_rounded``). Files that
carry run-specific values are compared after normalisation, and only those values are masked:

- the absolute temporary paths of this run (``<out>``, ``<store>``, ``<source>``),
- wall-clock times (ISO timestamps, Great Expectations run ids, ``*seconds`` fields and timings),
- sha256 digests and byte sizes inside JSON/Markdown, and the card's short gate-binding id (they
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
    if isinstance(value, dict):
        return {k: ("<masked>" if _VOLATILE_KEY.search(k) else _mask_json(v, bases, k))
                for k, v in sorted(value.items())}
    if isinstance(value, list):
        return [_mask_json(v, bases, key) for v in value]
    if isinstance(value, str):
        return _mask_text(value, bases)
    return value


def _rounded(value):
    """A table cell for the golden document: floats to 9 significant digits (NaN and inf as text)."""
    if isinstance(value, float):
        return float(f"{value:.9g}") if value == value and abs(value) != float("inf") else str(value)
    if isinstance(value, list):
        return [_rounded(v) for v in value]
    if isinstance(value, dict):
        return {k: _rounded(v) for k, v in value.items()}
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
            # data tables (clips, frames): their content exactly, by digest (the parquet bytes
            # themselves may change with the pyarrow version)
            doc = {"schema": [f"{f.name}:{f.type}" for f in table.schema], "rows": table.to_pydict()}
            return hashlib.sha256(json.dumps(doc, sort_keys=True, default=str).encode()).hexdigest()
        # statistics tables: the table itself, so that a diff names the column that changed; floats
        # to 9 significant digits: statistics such as residuals and percentiles differ in their
        # last bits between numpy/BLAS builds, which is not a change of behaviour
        return {"schema": [f"{f.name}:{f.type}" for f in table.schema],
                "columns": {name: [_rounded(v) for v in values] for name, values in table.to_pydict().items()}}
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
        changed = sorted(k for k in set(golden[tree]) & set(digest[tree]) if golden[tree][k] != digest[tree][k])
        for k in changed[:3]:
            print(f"--- {tree}/{k}\n{json.dumps(golden[tree][k], indent=1)[:3000]}\n+++\n"
                  f"{json.dumps(digest[tree][k], indent=1)[:3000]}")
        assert not (missing or extra or changed), (
            f"{tree}: files missing {missing}, new {extra}, changed {changed} "
            f"(see the module docstring to regenerate after an intended change)")
