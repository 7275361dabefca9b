"""What a gate report validated: the binding between a report and the content of a folder.

A gate verdict is worth something only for the data it was computed on. ``run_gates`` writes into
its report a *binding*:

    {"format": "drivetrack-gates-binding/1",
     "tables": {"stats/objects.parquet": "<sha256>", ...},   every statistics table the gates read
     "clips": [["clips/training/<segment>.parquet", size, "<sha256>"], ...],   every clip data file, sorted
     "clips_sha256": "<sha256 of the sorted clip list>",
     "config_sha256": "<the gate configuration's fingerprint>",
     "sha256": "<sha256 of the canonical JSON of the four fields above>"}

``drivetrack.release.publish_release`` recomputes the same binding over exactly what it stages and
refuses a report whose binding differs (:func:`binding_problems` names the files). Clip data files
are the v2 clips and frames tables (:func:`drivetrack.outputs.parse_table_path`); exported npz
clips are derived from them and not bound. Plain Python: no
Great Expectations import.
"""
from __future__ import annotations

import hashlib
import json
import posixpath
from concurrent.futures import ThreadPoolExecutor

from drivetrack.outputs import parse_table_path

BINDING_FORMAT = "drivetrack-gates-binding/1"
HASH_CHUNK = 8 << 20


def _canonical(obj) -> bytes:
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), ensure_ascii=True).encode("ascii")


def clips_digest(clips) -> str:
    """sha256 of the sorted ``(path, size, sha256)`` list (one ``path\\tsize\\tsha256\\n`` line each)."""
    h = hashlib.sha256()
    for path, size, digest in sorted((str(p), int(s), str(d)) for p, s, d in clips):
        h.update(f"{path}\t{size}\t{digest}\n".encode())
    return h.hexdigest()


def make_binding(tables: dict[str, str], clips, config_sha256: str) -> dict:
    """The binding of ``tables`` (``{relative path: sha256}``), ``clips`` (``(path, size, sha256)``
    triples, relative paths) and the gate configuration fingerprint ``config_sha256``."""
    body = {"format": BINDING_FORMAT,
            "tables": {str(k): str(v) for k, v in sorted(tables.items())},
            "clips": [[p, s, d] for p, s, d in sorted((str(p), int(s), str(d)) for p, s, d in clips)],
            "config_sha256": str(config_sha256)}
    body["clips_sha256"] = clips_digest(body["clips"])
    body["sha256"] = hashlib.sha256(_canonical(body)).hexdigest()
    return body


def _hash_file(fs, path: str) -> tuple[str, int]:
    h = hashlib.sha256()
    n = 0
    with fs.open(path, "rb") as f:
        while chunk := f.read(HASH_CHUNK):
            h.update(chunk)
            n += len(chunk)
    return h.hexdigest(), n


def folder_clips(fs, root: str, workers: int = 8) -> list[tuple[str, int, str]]:
    """``(relative path, size, sha256)`` of every clip file under ``root`` (a path of ``fs``), sorted."""
    root = root.rstrip("/")
    rels = sorted(rel for rel in (p[len(root):].lstrip("/") for p in fs.find(root))
                  if parse_table_path(rel))
    if not rels:
        return []
    with ThreadPoolExecutor(max_workers=max(1, min(workers, len(rels)))) as pool:
        hashed = list(pool.map(lambda rel: _hash_file(fs, posixpath.join(root, rel)), rels))
    return [(rel, n, digest) for rel, (digest, n) in zip(rels, hashed)]


def check_binding_shape(binding, where: str) -> list[str]:
    """Problems with the structure and self-consistency of a binding (empty when it is sound)."""
    if not isinstance(binding, dict):
        return [f"{where}: the report holds no content binding (key 'binding'; written by "
                f"drivetrack.gates.run_gates since {BINDING_FORMAT}), so it cannot show which data it "
                f"validated"]
    if binding.get("format") != BINDING_FORMAT:
        return [f"{where}: binding format is {binding.get('format')!r}, expected {BINDING_FORMAT!r}"]
    tables, clips = binding.get("tables"), binding.get("clips")
    if not isinstance(tables, dict) or not isinstance(clips, list) or not all(
            isinstance(c, list) and len(c) == 3 for c in clips):
        return [f"{where}: binding 'tables' must map paths to sha256 and 'clips' list [path, size, sha256]"]
    try:
        again = make_binding(tables, clips, binding.get("config_sha256"))
    except (TypeError, ValueError) as e:
        return [f"{where}: binding cannot be read ({e})"]
    problems = []
    if again["clips_sha256"] != binding.get("clips_sha256"):
        problems.append(f"{where}: binding clips_sha256 is {binding.get('clips_sha256')} but its clip list "
                        f"hashes to {again['clips_sha256']}: the binding was edited")
    if again["sha256"] != binding.get("sha256"):
        problems.append(f"{where}: binding sha256 is {binding.get('sha256')} but its content hashes to "
                        f"{again['sha256']}: the binding was edited")
    return problems


def binding_problems(binding: dict, tables: dict[str, str | None], clips: dict[str, tuple[int, str | None]],
                     limit: int = 10) -> list[str]:
    """How the content (``tables``: ``{path: sha256}``, ``clips``: ``{path: (size, sha256)}``) differs
    from ``binding``; a ``None`` sha256 compares the size (or the presence) only."""
    problems: list[str] = []
    bound_tables = binding["tables"]
    for path in sorted(set(bound_tables) | set(tables)):
        if path not in tables:
            problems.append(f"{path}: validated by the gates but not in the folder being published")
        elif path not in bound_tables:
            problems.append(f"{path}: in the folder being published but not validated by the gates")
        elif tables[path] is not None and tables[path] != bound_tables[path]:
            problems.append(f"{path}: sha256 {tables[path]}, the gates validated sha256 {bound_tables[path]}")
    bound_clips = {p: (int(s), d) for p, s, d in binding["clips"]}
    for path in sorted(set(bound_clips) | set(clips)):
        if path not in clips:
            problems.append(f"{path}: a clip file when the gates ran, missing from the folder being published")
        elif path not in bound_clips:
            problems.append(f"{path}: clip file not present when the gates ran")
        else:
            size, digest = clips[path]
            if size != bound_clips[path][0]:
                problems.append(f"{path}: {size} bytes, {bound_clips[path][0]} bytes when the gates ran")
            elif digest is not None and digest != bound_clips[path][1]:
                problems.append(f"{path}: sha256 {digest}, sha256 {bound_clips[path][1]} when the gates ran")
    if len(problems) > limit:
        problems = problems[:limit] + [f"and {len(problems) - limit} more"]
    return problems
