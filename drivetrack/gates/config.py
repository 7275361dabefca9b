"""Gate configuration: the versioned defaults plus an optional override.

The defaults ship inside the package as ``drivetrack/gates/default_gates.yaml`` (package data,
read with :mod:`importlib.resources`, so a wheel install has them); ``infra/gates.yaml`` is a
symbolic link to that one file.

The file holds one entry per gate as ``{value, reason}``. An override (a YAML file or a dict) is
deep-merged over the defaults; it may give a plain value (the default reason is kept, marked as
overridden) or ``{value, reason}``. Unknown sections or keys raise :class:`GateConfigError` so that
a typo cannot silently switch a gate off.
"""
from __future__ import annotations

import copy
import hashlib
import json
from importlib import resources
from pathlib import Path
from typing import Any

import yaml

#: The versioned defaults shipped with the package (``infra/gates.yaml`` links to this file).
DEFAULT_CONFIG_PATH = resources.files(__package__).joinpath("default_gates.yaml")

#: Sections whose entries are gates ({value, reason}).
GATE_SECTIONS = ("object", "segment", "release")
#: Percentile names of the speed-error columns (``speed_err_<p>``).
PERCENTILES = ("p25", "p50", "p75", "p95", "p99")


class GateConfigError(ValueError):
    """The gate configuration is malformed: names the file (or 'dict'), the key and the value."""


def _read_yaml(path) -> dict:
    path = path if hasattr(path, "read_text") else Path(path)   # a Path or an importlib Traversable
    if not path.is_file():
        raise GateConfigError(f"gate configuration file {path} does not exist")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise GateConfigError(f"gate configuration file {path} is not valid YAML: {exc}") from exc
    if not isinstance(data, dict):
        raise GateConfigError(f"gate configuration file {path}: top level must be a mapping, "
                              f"found {type(data).__name__}")
    return data


def _check_defaults(defaults: dict, source: str) -> None:
    for section in GATE_SECTIONS:
        entries = defaults.get(section)
        if not isinstance(entries, dict):
            raise GateConfigError(f"{source}: section '{section}' is missing or not a mapping")
        for key, entry in entries.items():
            if not (isinstance(entry, dict) and set(entry) == {"value", "reason"}):
                raise GateConfigError(f"{source}: '{section}.{key}' must be a mapping with exactly "
                                      f"'value' and 'reason', found {entry!r}")
    paper = defaults.get("paper_speed_err_median_mps")
    if not isinstance(paper, dict) or set(paper) != set(PERCENTILES):
        raise GateConfigError(f"{source}: 'paper_speed_err_median_mps' must map exactly "
                              f"{list(PERCENTILES)} to m/s, found {paper!r}")


def _merge(defaults: dict, override: dict, source: str) -> dict:
    merged = copy.deepcopy(defaults)
    for section, entries in override.items():
        if section == "version":
            if entries != defaults.get("version"):
                raise GateConfigError(f"{source}: version {entries!r} differs from the supported "
                                      f"version {defaults.get('version')!r}")
            continue
        if section == "paper_speed_err_median_mps":
            if not isinstance(entries, dict) or not set(entries) <= set(PERCENTILES):
                raise GateConfigError(f"{source}: 'paper_speed_err_median_mps' keys must be among "
                                      f"{list(PERCENTILES)}, found {entries!r}")
            merged[section].update({k: float(v) for k, v in entries.items()})
            continue
        if section not in GATE_SECTIONS:
            raise GateConfigError(f"{source}: unknown section '{section}' (known: version, "
                                  f"paper_speed_err_median_mps, {', '.join(GATE_SECTIONS)})")
        if not isinstance(entries, dict):
            raise GateConfigError(f"{source}: section '{section}' must be a mapping, "
                                  f"found {entries!r}")
        for key, entry in entries.items():
            if key not in merged[section]:
                raise GateConfigError(f"{source}: unknown gate '{section}.{key}' (known: "
                                      f"{', '.join(sorted(merged[section]))})")
            if isinstance(entry, dict) and set(entry) <= {"value", "reason"} and "value" in entry:
                value = entry["value"]
                reason = entry.get("reason", merged[section][key]["reason"] + f" [overridden by {source}]")
            else:
                value = entry
                reason = merged[section][key]["reason"] + f" [overridden by {source}]"
            old = merged[section][key]["value"]
            if isinstance(old, dict) and isinstance(value, dict):
                value = {**old, **value}  # mapping-valued gates: override entries by name
            merged[section][key] = {"value": value, "reason": reason}
    return merged


def _check_values(cfg: dict, source: str) -> None:
    def number(section: str, key: str, lo: float | None = None, hi: float | None = None) -> None:
        value = cfg[section][key]["value"]
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise GateConfigError(f"{source}: '{section}.{key}' must be a number, found {value!r}")
        if (lo is not None and value < lo) or (hi is not None and value > hi):
            raise GateConfigError(f"{source}: '{section}.{key}' = {value!r} outside "
                                  f"[{lo}, {hi}]")

    def flag(section: str, key: str) -> None:
        value = cfg[section][key]["value"]
        if not isinstance(value, bool):
            raise GateConfigError(f"{source}: '{section}.{key}' must be true or false, "
                                  f"found {value!r}")

    def str_list(section: str, key: str) -> None:
        value = cfg[section][key]["value"]
        if not (isinstance(value, list) and all(isinstance(v, str) for v in value)):
            raise GateConfigError(f"{source}: '{section}.{key}' must be a list of strings, "
                                  f"found {value!r}")

    for key in ("speed_err_p50_max_mps", "speed_err_p95_max_mps", "visible_fraction_max",
                "max_min_camera_distance_m"):
        number("object", key, lo=0)
    number("object", "speed_err_mostly", lo=0, hi=1)
    number("object", "visible_fraction_min", lo=0, hi=1)
    number("object", "ambiguous_occlusion_fraction_max", lo=0, hi=1)
    for key in ("min_num_tracks", "max_nonfinite_visible", "max_visible_outside_image",
                "min_num_frames"):
        number("object", key, lo=0)
    flag("object", "require_files")
    str_list("segment", "allowed_status")
    number("segment", "min_object_clips_annotated", lo=0)
    number("segment", "rejected_share_min_considered", lo=0)
    flag("segment", "check_rejections_table")
    shares = cfg["segment"]["rejected_share_max"]["value"]
    if not isinstance(shares, dict) or "default" not in shares:
        raise GateConfigError(f"{source}: 'segment.rejected_share_max' must be a mapping of filter "
                              f"reason to share with a 'default' entry, found {shares!r}")
    for reason, share in shares.items():
        if isinstance(share, bool) or not isinstance(share, (int, float)) or not 0 <= share <= 1:
            raise GateConfigError(f"{source}: 'segment.rejected_share_max.{reason}' must be a "
                                  f"share in [0, 1], found {share!r}")
    number("release", "speed_err_median_margin", lo=0)
    number("release", "speed_err_median_min_mps", lo=0)
    for key in ("min_total_tracks", "min_objects_per_split", "min_tracks_per_split"):
        number("release", key, lo=0)
    str_list("release", "required_splits")
    flag("release", "check_split_files")
    for p in PERCENTILES:
        v = cfg["paper_speed_err_median_mps"][p]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or v <= 0:
            raise GateConfigError(f"{source}: 'paper_speed_err_median_mps.{p}' must be a positive "
                                  f"number of m/s, found {v!r}")


def load_gate_config(config: str | Path | dict | None = None,
                     defaults_path: str | Path | None = None) -> dict:
    """The effective gate configuration: defaults (``default_gates.yaml``) merged with ``config``.

    ``config`` is None (defaults only), a path to a YAML file, or a dict of the same shape. The
    result has every gate as ``{"value": ..., "reason": ...}`` and a ``source`` entry.
    """
    defaults_path = Path(defaults_path) if defaults_path else DEFAULT_CONFIG_PATH
    defaults = _read_yaml(defaults_path)
    _check_defaults(defaults, str(defaults_path))
    if config is None:
        override, source = {}, None
    elif isinstance(config, dict):
        override, source = config, "dict"
    elif isinstance(config, (str, Path)):
        override, source = _read_yaml(config), str(config)
    else:
        raise GateConfigError(f"gate configuration must be None, a path or a dict, "
                              f"found {type(config).__name__}")
    merged = _merge(defaults, override, source or str(defaults_path))
    _check_values(merged, source or str(defaults_path))
    merged["source"] = {"defaults": str(defaults_path), "override": source}
    return merged


def config_sha256(cfg: dict) -> str:
    """sha256 of the effective configuration (canonical JSON), recorded in every report."""
    body = {k: v for k, v in cfg.items() if k != "source"}
    return hashlib.sha256(json.dumps(body, sort_keys=True, default=str).encode()).hexdigest()


def gate_value(cfg: dict, section: str, key: str) -> Any:
    return cfg[section][key]["value"]


def gate_reason(cfg: dict, section: str, key: str) -> str:
    return cfg[section][key]["reason"]
