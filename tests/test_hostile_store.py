"""Hostile inputs and faults for the release store's read and maintenance side (issue 13):
dataset names that would leave the store, names with a trailing newline, a publish killed at any
point of its writes and resumed once, and stores that cannot be reached."""
from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from test_release import make_output

from drivetrack.cli import main as cli
from drivetrack.release import (InvalidVersionError, ManifestError, list_versions, open_store, publish_release,
                                verify_release)

DS = "drivetrack-waymo"
OLD = 1_000_000_000  # an mtime far in the past: every lock and temporary looks stale


def snapshot(root: Path, skip: Path | None = None) -> dict:
    """Every folder and file below ``root`` (except below ``skip``) with its bytes and mode."""
    out = {}
    for dirpath, dirs, files in os.walk(root):
        if skip is not None and Path(dirpath).resolve().is_relative_to(skip.resolve()):
            continue
        for name in dirs:
            out[os.path.join(dirpath, name)] = "dir"
        for name in files:
            p = os.path.join(dirpath, name)
            out[p] = (Path(p).read_bytes(), os.stat(p).st_mode)
    return out


def plant_victim(folder: Path) -> None:
    """Files that a gc of a dataset at ``folder`` would delete: locks, temporaries, an old claim with
    staging and uncommitted version files, an index."""
    (folder / "_txn").mkdir(parents=True, exist_ok=True)
    (folder / "_txn" / "1.0.0.json").write_text(json.dumps({"txid": "x", "started_unix": 0}))
    (folder / "_staging" / "1.0.0").mkdir(parents=True, exist_ok=True)
    (folder / "_staging" / "1.0.0" / "data.bin").write_bytes(b"staged")
    (folder / "_staging" / "2.0.0").mkdir(parents=True, exist_ok=True)
    (folder / "_staging" / "2.0.0" / "data.bin").write_bytes(b"unclaimed")
    (folder / "1.0.0").mkdir(exist_ok=True)
    (folder / "1.0.0" / "keep.txt").write_bytes(b"precious")
    (folder / "versions.json").write_text('{"versions": []}')
    for name in ("a.lock", "versions.json.lock", "b.tmp-123", "1.0.0/c.tmp-9"):
        (folder / name).write_bytes(b"victim")
        os.utime(folder / name, (OLD, OLD))


# ---- item 1: gc, verify, versions, status and diff stay inside the store --------------------------

@pytest.fixture
def store_and_victims(tmp_path):
    """``stores/store`` holds a published release; ``stores/victim`` and ``stores`` itself hold files
    a dataset name such as ``../victim`` or ``..`` would reach."""
    base = tmp_path / "stores"
    store = base / "store"
    publish_release(make_output(tmp_path / "out", n_clips=1), store, "1.0.0")
    plant_victim(base / "victim")
    plant_victim(base)
    (base / "x\n").mkdir()
    plant_victim(base / "x\n")
    return store, base


BAD_DATASETS = ["../victim", "..", ".", "a/b", "x\n", "drivetrack-waymo\n", "../victim\n", "", "_txn",
                "-rf", "victim/../..", "a\x00b"]


@pytest.mark.parametrize("dataset", BAD_DATASETS + ["<absolute victim>"])
def test_bad_dataset_names_are_refused_before_any_path_is_built(store_and_victims, dataset, capsys):
    store, base = store_and_victims
    if dataset == "<absolute victim>":
        dataset = str(base / "victim")
    before = snapshot(base)
    commands = [
        ["gc", str(store), f"--dataset={dataset}", "--older-than", "0"],
        ["verify", str(store), "--version", "1.0.0", f"--dataset={dataset}"],
        ["verify", str(store), "--version", "latest", f"--dataset={dataset}"],
        ["versions", str(store), f"--dataset={dataset}"],
        ["status", str(store), "--print", f"--dataset={dataset}"],
        ["diff", str(store), "1.0.0", "1.0.0", f"--dataset={dataset}"],
    ]
    for argv in commands:
        code = cli(argv)
        err = capsys.readouterr().err
        assert code == 2, (argv, code, err)
        assert "dataset name" in err and repr(dataset) in err, (argv, err)
        assert snapshot(base) == before, f"{argv} changed files outside (or inside) the store"
    from drivetrack.release import gc

    with pytest.raises(ValueError, match="dataset name"):
        gc(store, dataset, older_than_s=0)
    assert snapshot(base) == before


def test_store_refuses_paths_that_leave_its_root(tmp_path):
    from drivetrack.release.errors import UnsafeStorePathError

    base = tmp_path / "stores"
    store = open_store(base / "store")
    plant_victim(base / "victim")
    before = snapshot(base)
    bad = ["../victim", "..", ".", "a/../../victim", "/etc", str(base / "victim"), "a//b", "a/", "/",
           "x\n", "a\rb", "a\x00b", "a\\..\\b", "victim/./a.lock"]
    for rel in bad:
        calls = {
            "path": lambda: store.path(rel), "exists": lambda: store.exists(rel),
            "find": lambda: store.find(rel), "list_dirs": lambda: store.list_dirs(rel),
            "delete": lambda: store.delete(f"{rel}/a.lock"), "delete_tree": lambda: store.delete_tree(rel),
            "write_bytes": lambda: store.write_bytes(f"{rel}/w", b"1"),
            "put_if_absent": lambda: store.put_if_absent(f"{rel}/p", b"1"),
            "compare_and_swap": lambda: store.compare_and_swap(f"{rel}/c", b"1", None),
            "move": lambda: store.move("src", f"{rel}/m"), "prune_empty": lambda: store.prune_empty(rel),
        }
        for name, call in calls.items():
            with pytest.raises(UnsafeStorePathError, match="not allowed in a store"):
                call()
    assert snapshot(base) == before


def test_gc_does_not_delete_through_a_symlinked_dataset_folder(tmp_path):
    base = tmp_path / "stores"
    (base / "store").mkdir(parents=True)
    plant_victim(base / "victim")
    os.symlink(base / "victim", base / "store" / "linked")
    before = snapshot(base / "victim")
    from drivetrack.release import gc

    with pytest.raises(ValueError, match="outside the store"):
        gc(base / "store", "linked", older_than_s=0)
    assert snapshot(base / "victim") == before


def test_gc_never_deletes_committed_files_named_like_locks_or_temporaries(tmp_path):
    # Publish ships only members of the output contract (no '*.lock' can be one); a Data Docs page
    # may still carry '.tmp-' in its name.
    src = make_output(tmp_path / "out", n_clips=1)
    (src / "validation" / "data_docs").mkdir(parents=True, exist_ok=True)
    (src / "validation" / "data_docs" / "x.tmp-1.html").write_text("a release file, not a temporary")
    store = tmp_path / "store"
    publish_release(src, store, "1.0.0")
    for p in (store / DS / "1.0.0" / "validation" / "data_docs").iterdir():
        os.utime(p, (OLD, OLD))
    from drivetrack.release import gc

    gc(store, DS, older_than_s=0)
    assert verify_release(store, "1.0.0").ok


# ---- item 2: names with a trailing newline ---------------------------------------------------------

def test_names_with_a_trailing_newline_are_refused(tmp_path, capsys):
    src = make_output(tmp_path / "out", n_clips=1)
    store = tmp_path / "store"
    with pytest.raises(InvalidVersionError):
        publish_release(src, store, "1.0.0\n")
    with pytest.raises(ValueError, match="dataset name"):
        publish_release(src, store, "1.0.0", dataset="dsx\n")
    assert not store.exists() or not any(store.iterdir())
    gates = src / "validation" / "gates.json"  # the folder's own report, bound to its content
    for argv in (["--version", "1.0.0\n"], ["--version", "1.0.0", "--dataset", "dsx\n"]):
        assert cli(["publish", str(src), "--store", str(store), "--gate-report", str(gates)] + argv) != 0
    capsys.readouterr()
    assert not store.exists() or not any(store.iterdir())
    # Beside a real 1.0.0: the readers refuse the newline too.
    publish_release(src, store, "1.0.0")
    with pytest.raises(InvalidVersionError):
        verify_release(store, "1.0.0\n")
    assert cli(["verify", str(store), "--version", "1.0.0\n"]) == 2
    assert [p.name for p in (store / DS).iterdir() if "\n" in p.name] == []


def test_a_folder_named_with_a_newline_is_not_a_version(tmp_path):
    store = tmp_path / "store"
    publish_release(make_output(tmp_path / "out", n_clips=1), store, "1.0.0")
    fake = store / DS / "1.0.1\n"
    fake.mkdir()
    (fake / "manifest.json").write_bytes((store / DS / "1.0.0" / "manifest.json").read_bytes())
    assert [v["version"] for v in list_versions(store)] == ["1.0.0"]


def test_latest_pointer_naming_a_path_is_refused(tmp_path):
    store = tmp_path / "store"
    publish_release(make_output(tmp_path / "out", n_clips=1), store, "1.0.0")
    latest = store / DS / "latest.json"
    os.chmod(latest, 0o644)
    latest.write_text(json.dumps({"version": "../../victim"}))
    with pytest.raises(ManifestError, match="not a semantic version"):
        verify_release(store, "latest")


# ---- item 5: a publish killed at any point, then one --resume -------------------------------------

DRIVER = textwrap.dedent('''
    """Publish in forked children, each killed (os._exit, no clean-up) just before its K-th write-side
    file operation in the store; then ONE resume per store in another forked child."""
    import builtins, json, os, sys, traceback

    from drivetrack.release import publish_release
    from drivetrack.release.store import LocalConditional

    src, stores, mode = sys.argv[1], sys.argv[2], sys.argv[3]
    with open(os.path.join(src, "validation", "gates.json")) as f:
        REPORT = json.load(f)  # the folder's own gate report, bound to its content
    OPS = ("link", "replace", "rename", "unlink", "rmdir", "mkdir", "chmod", "open")


    def install(root, kill_at, log):
        count = [0]

        def wrap(mod, name):
            orig = getattr(mod, name)

            def op(*a, **k):
                p = a[0] if a else None
                if isinstance(p, str) and p.startswith(root):
                    count[0] += 1
                    log.append((name, p[len(root):]))
                    if count[0] == kill_at:
                        os._exit(137)
                return orig(*a, **k)
            setattr(mod, name, op)
        for name in OPS:
            wrap(os, name)
        wrap(builtins, "open")


    def child(fn):
        pid = os.fork()
        if pid == 0:
            try:
                fn()
                os._exit(0)
            except BaseException:
                traceback.print_exc()
                os._exit(3)
        return os.waitstatus_to_exitcode(os.waitpid(pid, 0)[1])


    if mode == "count":
        root = os.path.join(stores, "count")
        log = []
        install(root, 0, log)
        publish_release(src, root, "1.0.0", workers=1, gate_report=REPORT)
        print(json.dumps(log))
    else:
        points = json.loads(sys.argv[4])
        # One publish first, so that the forked children do not each import pandas/pyarrow lazily.
        publish_release(src, os.path.join(stores, "warm"), "1.0.0", workers=1, gate_report=REPORT)
        out = {}
        for k in points:
            root = os.path.join(stores, f"k{k}")
            killed = child(lambda: (install(root, k, []), publish_release(src, root, "1.0.0", workers=1, gate_report=REPORT)))

            def resume():
                LocalConditional.lock_timeout_s = 0.3  # a lock left by the killed process: wait 0.3 s, not 10
                publish_release(src, root, "1.0.0", workers=1, resume=True, gate_report=REPORT)
            out[k] = {"killed": killed, "resume": child(resume) if mode == "kill+resume" else None}
        print(json.dumps(out))
''')


def run_driver(tmp_path, src, stores, *args) -> dict | list:
    driver = tmp_path / "driver.py"
    driver.write_text(DRIVER)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(Path(__file__).parents[1])] + sys.path)}
    done = subprocess.run([sys.executable, str(driver), str(src), str(stores), *args], capture_output=True,
                          text=True, timeout=300, env=env)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_publish_killed_at_any_point_then_one_resume_verifies_clean(tmp_path):
    src = make_output(tmp_path / "out", n_clips=1)
    stores = tmp_path / "stores"
    log = run_driver(tmp_path, src, stores, "count")
    # Every operation but mkdir from just before the manifest's temporary on (the commit and all
    # after it: index, latest pointer, clean-up), and every 8th operation before (claim, staging,
    # promotion).
    first_manifest = next(i for i, (_, p) in enumerate(log) if "manifest.json" in p)
    points = sorted({i + 1 for i, (op, p) in enumerate(log)
                     if (i >= first_manifest - 2 and op != "mkdir") or i % 8 == 0})
    assert len(points) >= 20, log
    results = run_driver(tmp_path, src, stores, "kill+resume", json.dumps(points))
    problems = []
    for k, r in sorted(results.items(), key=lambda kv: int(kv[0])):
        op, path = log[int(k) - 1]
        assert r["killed"] == 137, f"kill point {k} ({op} {path}) was not reached: {r}"
        if r["resume"] != 0:
            problems.append(f"kill before {op} {path}: --resume exited {r['resume']}")
            continue
        root = stores / f"k{k}"
        report = verify_release(root, "1.0.0")
        if not report.ok:
            problems.append(f"kill before {op} {path}: verify after one resume: extra {report.extra}, "
                            f"missing {report.missing}, corrupt {report.corrupt}")
        leftovers = [p for p in (root / DS).rglob("*") if ".tmp-" in p.name]
        if leftovers:
            problems.append(f"kill before {op} {path}: temporaries in the dataset folder {leftovers}")
    assert not problems, "\n".join(problems)


def test_cli_resume_after_a_kill_inside_the_manifest_commit(tmp_path):
    """The same through the real command line: kill between the manifest's temporary and its link."""
    src = make_output(tmp_path / "out", n_clips=1)
    stores = tmp_path / "stores"
    log = run_driver(tmp_path, src, stores, "count")
    # Just before the unlink of the manifest's temporary: linked (committed), temporary still there.
    k = next(i for i, (op, p) in enumerate(log) if op == "link" and "manifest.json" in p) + 2
    assert run_driver(tmp_path, src, stores, "kill", json.dumps([k]))[str(k)]["killed"] == 137
    gates = src / "validation" / "gates.json"  # the folder's own report, bound to its content
    root = stores / f"k{k}"
    done = subprocess.run([sys.executable, "-m", "drivetrack.cli", "publish", str(src), "--store", str(root),
                           "--version", "1.0.0", "--gate-report", str(gates), "--resume"],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert verify_release(root, "1.0.0").ok
    assert [v["version"] for v in list_versions(root) if v["latest"]] == ["1.0.0"]


def test_resume_of_a_committed_version_with_other_content_is_refused(tmp_path):
    from drivetrack.release import VersionExistsError

    store = tmp_path / "store"
    publish_release(make_output(tmp_path / "a", n_clips=1), store, "1.0.0")
    with pytest.raises(VersionExistsError, match="other content"):
        publish_release(make_output(tmp_path / "b", seed=3, n_clips=1), store, "1.0.0", resume=True)
    assert verify_release(store, "1.0.0").ok


# ---- item 9: a store that cannot be reached ---------------------------------------------------------

@pytest.fixture
def closed_endpoint(monkeypatch):
    """An http:// URL on loopback where nothing listens (a port bound, then closed)."""
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    monkeypatch.setenv("AWS_ACCESS_KEY_ID", "testing")
    monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", "testing")
    monkeypatch.setenv("AWS_MAX_ATTEMPTS", "1")  # botocore: one attempt
    import s3fs

    monkeypatch.setattr(s3fs.S3FileSystem, "retries", 1)  # s3fs: no retry loop (test speed only)
    return f"http://127.0.0.1:{port}"


def test_unreachable_store_is_one_line_and_exit_code_4(tmp_path, closed_endpoint, capsys):
    url = "s3://no-bucket/releases"
    src = make_output(tmp_path / "out", n_clips=1)
    gates = src / "validation" / "gates.json"  # the folder's own report, bound to its content
    ep = ["--endpoint-url", closed_endpoint]
    commands = [
        ["verify", url, "--version", "1.0.0"] + ep,
        ["verify", url, "--version", "latest"] + ep,
        ["versions", url] + ep,
        ["gc", url, "--older-than", "0"] + ep,
        ["diff", url, "1.0.0", "1.1.0"] + ep,
        ["status", url, "--print"] + ep,
        ["publish", str(src), "--store", url, "--version", "1.0.0", "--gate-report", str(gates)] + ep,
        ["info", url, "--storage-option", f"endpoint_url={closed_endpoint}"],
    ]
    for argv in commands:
        code = cli(argv)
        out, err = capsys.readouterr()
        lines = err.strip().splitlines()
        assert code == 4, (argv, code, err[-2000:])
        assert 1 <= len(lines) <= 2 and "Traceback" not in err, (argv, err[-2000:])
        assert lines[0].startswith(f"drivetrack {argv[0]}: cannot reach ") and url in lines[0], lines
        assert closed_endpoint.removeprefix("http://") in lines[0], lines


def test_exit_codes_are_distinct_and_documented(tmp_path, capsys):
    store = tmp_path / "store"
    publish_release(make_output(tmp_path / "out", n_clips=1), store, "1.0.0")
    assert cli(["verify", str(store), "--version", "1.0.0"]) == 0
    f = store / DS / "1.0.0" / "run.json"
    os.chmod(f, 0o644)
    f.write_bytes(f.read_bytes() + b" ")
    assert cli(["verify", str(store), "--version", "1.0.0"]) == 1  # mismatch
    assert cli(["verify", str(store), "--version", "9.9.9"]) == 2  # not published
    capsys.readouterr()
    for command in ("verify", "versions", "gc", "diff", "status", "publish"):
        with pytest.raises(SystemExit):
            cli([command, "--help"])
        text = " ".join(capsys.readouterr().out.split())
        assert "exit codes: 0 ok; 1 failed" in text and "4 cannot reach the store" in text, command
    with pytest.raises(SystemExit):
        cli(["info", "--help"])
    assert "4 cannot reach ROOT" in " ".join(capsys.readouterr().out.split())
