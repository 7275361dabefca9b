"""Progress on long work (issue 17.5): publish, verify and gates report progress events that size
and fill one rich bar, and the commands draw it on stderr (not with --json)."""
from __future__ import annotations

import io

from test_release import gates_of, make_output

from drivetrack.cli import main
from drivetrack.gates import run_gates
from drivetrack.release import publish_release, verify_release


def _recorder():
    events = []
    return events, lambda event, info: events.append((event, dict(info)))


def test_publish_and_verify_plan_then_account_for_every_byte(tmp_path):
    src = make_output(tmp_path / "out", n_clips=1)
    store = tmp_path / "store"
    events, progress = _recorder()
    result = publish_release(src, store, "1.0.0", gate_report=gates_of(src), progress=progress)
    planned = [info for e, info in events if e == "planned"]
    uploaded = [info for e, info in events if e == "uploaded"]
    assert len(planned) == 1 and planned[0]["files"] == len(uploaded)
    assert planned[0]["bytes"] == sum(u["bytes"] for u in uploaded) > 0
    assert [e for e, _ in events].index("planned") < [e for e, _ in events].index("uploaded")

    events, progress = _recorder()
    report = verify_release(store, "1.0.0", progress=progress)
    planned = [info for e, info in events if e == "planned"]
    checked = [info for e, info in events if e == "checked"]
    assert report.ok and planned[0]["files"] == len(checked) == report.files_checked
    assert planned[0]["bytes"] == sum(c["bytes"] for c in checked) == report.bytes
    assert result.files >= report.files_checked


def test_gates_plan_their_steps(tmp_path):
    src = make_output(tmp_path / "out", n_clips=1)
    events, progress = _recorder()
    run_gates(str(src), data_docs=False, progress=progress)
    kinds = [e for e, _ in events]
    assert kinds[0] == "planned" and events[0][1]["steps"] == kinds.count("validated") > 0


def test_commands_draw_a_bar_on_stderr_and_none_with_json(tmp_path, monkeypatch, capsys):
    from rich.console import Console

    import drivetrack.commands._progress as bars

    screen = io.StringIO()
    monkeypatch.setattr(bars, "_console", lambda: Console(file=screen, force_terminal=True, width=120))
    src = make_output(tmp_path / "out", n_clips=1)
    store = tmp_path / "store"
    assert main(["publish", str(src), "--store", str(store), "--version", "1.0.0",
                 "--gate-report", str(src / "validation" / "gates.json")]) == 0
    assert main(["verify", str(store), "--version", "1.0.0"]) == 0
    assert main(["gates", str(src), "--no-data-docs"]) == 0
    drawn = screen.getvalue()
    for label in ("publish", "verify", "gates"):
        assert label in drawn, f"no {label} bar in {drawn[-500:]!r}"
    assert "100%" in drawn or "MB" in drawn or "kB" in drawn
    screen.truncate(0)
    screen.seek(0)
    assert main(["verify", str(store), "--version", "1.0.0", "--json"]) == 0
    assert screen.getvalue() == ""
    capsys.readouterr()
