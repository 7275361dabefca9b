"""Release gates: Great Expectations suites built from ``infra/gates.yaml``.

Public API (Great Expectations is imported lazily, only inside :func:`run_gates`):

- ``run_gates(out_dir, config=None) -> GateReport``: validate ``OUT/stats/*.parquet``, write
  ``OUT/validation/`` (gates.json, report.html, gx_results/, data_docs/).
- ``card_summary(report, accepted_reason=None) -> str``: markdown section for the dataset card.
- ``failure_lines(report) -> list[str]``: one line per failed gate (CLI, logs, exceptions).
- ``load_gate_config(config=None) -> dict``: effective configuration (defaults + override).

``report.to_dict()`` (plain JSON types) is what ``publish_release(gate_report=...)`` takes.
"""
from drivetrack.gates.config import DEFAULT_CONFIG_PATH, GateConfigError, load_gate_config
from drivetrack.gates.report import GateReport, GateResult, card_summary, failure_lines
from drivetrack.gates.tables import GateInputError


def run_gates(out_dir: str, config: "str | dict | None" = None, *,
              data_docs: bool = True, progress=None) -> GateReport:
    """See :func:`drivetrack.gates.run.run_gates` (imported lazily: Great Expectations is slow to import)."""
    from drivetrack.gates.run import run_gates as _run

    return _run(out_dir, config, data_docs=data_docs, progress=progress)


__all__ = ["run_gates", "card_summary", "failure_lines", "load_gate_config", "GateReport",
           "GateResult", "GateConfigError", "GateInputError", "DEFAULT_CONFIG_PATH"]
