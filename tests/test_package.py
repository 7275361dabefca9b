"""The package's shape: a pure core that never imports Prefect, and a code fingerprint whose
modules are declared (drivetrack.release.keys), so that no module silently escapes the cache keys."""
from __future__ import annotations

import pkgutil
import subprocess
import sys
from pathlib import Path

import drivetrack
from drivetrack.release import keys

REPO = Path(__file__).resolve().parents[1]


def _package_modules() -> set[str]:
    return {"drivetrack"} | {m.name for m in pkgutil.walk_packages(drivetrack.__path__, "drivetrack.")}


def test_every_module_is_declared_output_or_release_code_exactly_once():
    output, release = set(keys.OUTPUT_MODULES), set(keys.RELEASE_MODULES)
    assert len(output) == len(keys.OUTPUT_MODULES) and len(release) == len(keys.RELEASE_MODULES), "listed twice"
    assert not output & release, f"declared both output and release code: {sorted(output & release)}"
    modules = _package_modules()
    undeclared = sorted(modules - output - release)
    assert not undeclared, (f"modules missing from drivetrack/release/keys.py (OUTPUT_MODULES if they can change "
                            f"a segment's outputs, else RELEASE_MODULES): {undeclared}")
    gone = sorted((output | release) - modules)
    assert not gone, f"declared modules that do not exist (moved or renamed?): {gone}"


def test_the_fingerprint_follows_declared_code_not_file_paths(monkeypatch):
    both, outputs = keys.code_fingerprint(), keys.code_fingerprint(outputs_only=True)
    assert len(both) == 64 and both != outputs
    # release-only code leaves the segment key's code part alone, output code changes it
    monkeypatch.setattr(keys, "RELEASE_MODULES", keys.RELEASE_MODULES[:-1])
    assert keys.code_fingerprint(outputs_only=True) == outputs and keys.code_fingerprint() != both
    monkeypatch.setattr(keys, "OUTPUT_MODULES", keys.OUTPUT_MODULES[:-1])
    assert keys.code_fingerprint(outputs_only=True) != outputs


def test_importing_every_drivetrack_module_never_imports_prefect():
    code = ("import pkgutil, sys, importlib, drivetrack\n"
            "names = [m.name for m in pkgutil.walk_packages(drivetrack.__path__, 'drivetrack.')]\n"
            "for n in names: importlib.import_module(n)\n"
            "bad = sorted(m for m in sys.modules if m == 'prefect' or m.startswith('prefect.'))\n"
            "print(len(names), bad)\n"
            "sys.exit(1 if bad else 0)\n")
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=300,
                          env={**__import__("os").environ, "PYTHONPATH": str(REPO)})
    assert proc.returncode == 0, f"importing drivetrack pulled in prefect: {proc.stdout} {proc.stderr[-2000:]}"
    assert int(proc.stdout.split()[0]) > 40


def test_architecture_map_lists_every_module():
    """docs/architecture.md's module map matches the tree: every module of drivetrack/ and flows/
    has a row, and no row names a module that is gone (issue 14)."""
    import re
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    doc = (root / "docs" / "architecture.md").read_text()
    listed = set(re.findall(r"^\| `((?:drivetrack|flows)/[^`]+\.py)` \|", doc, re.M))
    present = {p.relative_to(root).as_posix() for d in ("drivetrack", "flows") for p in (root / d).rglob("*.py")}
    assert not present - listed, f"modules missing from the map in docs/architecture.md: {sorted(present - listed)}"
    assert not listed - present, f"rows for modules that do not exist: {sorted(listed - present)}"
