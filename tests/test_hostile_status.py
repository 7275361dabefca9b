"""Hostile input for the status page and `drivetrack status` (issue 13 item 10): every link the
page renders from data is a relative path inside the release or dropped, everything rendered
from data is escaped, and the server hands out nothing but the page, its JSON and the files
under the release's previews/."""
from __future__ import annotations

import http.client
import json
import re
from html.parser import HTMLParser
import subprocess
import sys
from pathlib import Path

import pytest

from drivetrack.release.status import SEGMENT_STAGES, ReleaseStatus, StatusError, write_status
from drivetrack.release.status_pages import render_status_html

HOSTILE_LINKS = ["javascript:alert(1)", "JaVaScRiPt:alert(1)//x.png", "//evil.example/x.png",
                 "https://evil.example/x.png", "../../etc/passwd", "previews/../../etc/passwd.png",
                 "/etc/passwd.png", "previews/x.png\" onerror=\"alert(1)", "data:image/png;base64,AAAA",
                 "previews/.hidden.png", "previews\\..\\x.png", " previews/x.png", "previews/a.png\n"]
SCRIPT = "<script>alert('pwned')</script>"
GOOD = "previews/training/waymo_good_clip.png"


class _Tags(HTMLParser):
    """Every tag and attribute of a page, as a browser's tokenizer sees them."""

    def __init__(self, page: str):
        super().__init__(convert_charrefs=True)
        self.tags, self.attrs = [], []
        self.feed(page)

    def handle_starttag(self, tag, attrs):
        self.tags.append(tag)
        self.attrs += [(tag, k, v) for k, v in attrs]


def _assert_safe(page: str) -> None:
    parsed = _Tags(page)
    assert not {"script", "iframe", "object", "embed", "base", "form"} & set(parsed.tags), parsed.tags
    for tag, name, value in parsed.attrs:
        assert not name.startswith("on"), (tag, name, value)
        if name in ("href", "src", "action", "formaction", "poster", "srcset"):
            assert re.fullmatch(r"[A-Za-z0-9_\-][A-Za-z0-9_.\-]*(/[A-Za-z0-9_\-][A-Za-z0-9_.\-]*)*/?", value or ""), \
                (tag, name, value)
            assert ".." not in value.split("/"), value


def hostile_status() -> ReleaseStatus:
    st = ReleaseStatus(dataset="drivetrack-waymo", version="6.6.6", source=SCRIPT, store="<b>store</b>")
    st.message = SCRIPT
    for seg in ("seg-a", "<img src=x onerror=alert(1)>"):
        st.add_segment("training", seg, key=SCRIPT)
        for s in SEGMENT_STAGES:
            st.update("training", seg, s, "done", count=3, unit=SCRIPT, worker=SCRIPT)
    st.update("training", "seg-a", "depth", "failed", error=f"ValueError: {SCRIPT} \" onmouseover=\"alert(1)")
    for name in st.stages:
        st.update_release(name, "done")
    st.previews = [*HOSTILE_LINKS, GOOD]
    return st


def test_page_links_only_relative_release_paths_and_escapes_data():
    page = render_status_html(hostile_status())
    _assert_safe(page)
    assert f'href="{GOOD}"' in page and f'src="{GOOD}"' in page
    assert "&lt;script&gt;alert(&#x27;pwned&#x27;)&lt;/script&gt;" in page


def test_gate_values_and_segment_ids_from_the_tables_are_escaped(tmp_path):
    """A gate report whose names, bounds, observed values and failing rows carry markup."""
    from drivetrack.release.status_pages import read_quality

    (tmp_path / "validation").mkdir()
    report = {"success": False, "results": [
        {"gate": f"object.{SCRIPT}", "success": False, "columns": ["speed_err_p50"], "observed": SCRIPT,
         "expected": {"max_value": SCRIPT}, "failing": [
             {"split": "training", "segment": "seg-a", "object_id": SCRIPT, "speed_err_p50": SCRIPT}]},
        {"gate": "release.x", "success": False, "observed": '<a href="javascript:alert(1)">x</a>',
         "expected": "<iframe>", "failing": []},
        "not even a dict"]}
    (tmp_path / "validation" / "gates.json").write_text(json.dumps(report))
    q = read_quality(str(tmp_path))
    assert q.gates_success is False and q.gates_failed == 2
    assert q.of("training", "seg-a")["gates"][0]["gate"] == f"object.{SCRIPT}"
    page = render_status_html(hostile_status(), quality=q)
    _assert_safe(page)
    assert "&lt;a href=&quot;javascript:alert(1)&quot;&gt;x&lt;/a&gt;" in page   # shown as text
    assert "speed_err_p50=&lt;script&gt;" in page and "&lt;iframe&gt;" in page


def test_status_json_with_wrong_types_is_refused_naming_the_field():
    doc = hostile_status().to_dict()
    doc["segments"][0]["stages"]["ingest"]["seconds"] = "1; DROP"
    with pytest.raises(StatusError, match=r"seg-a stage ingest: field 'seconds'"):
        ReleaseStatus.from_dict(doc)
    doc = hostile_status().to_dict()
    doc["message"] = {"html": SCRIPT}
    with pytest.raises(StatusError, match=r"field 'message'"):
        ReleaseStatus.from_dict(doc)
    doc = hostile_status().to_dict()
    doc["segments"][1]["stages"]["write"]["cached"] = "yes"
    with pytest.raises(StatusError, match=r"field 'cached'"):
        ReleaseStatus.from_dict(doc)


def _raw_get(port: int, path: str) -> tuple[int, str, bytes]:
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    conn.putrequest("GET", path, skip_host=False, skip_accept_encoding=True)
    conn.endheaders()
    r = conn.getresponse()
    body = r.read()
    conn.close()
    return r.status, r.getheader("Content-Type") or "", body


def test_served_release_renders_safe_page_and_serves_only_its_previews(tmp_path):
    from drivetrack.release import publish_release

    from test_release import gates_of, make_output

    src = make_output(tmp_path / "src", n_clips=1)
    st = hostile_status()
    write_status(str(src), st)
    # a status.html stored by some other writer, with a live javascript: link: never served as is
    (src / "status.html").write_text('<a href="javascript:alert(1)">x</a><script>alert(1)</script>')
    (src / "previews" / "training").mkdir(parents=True)
    png = b"\x89PNG\r\n\x1a\n" + b"\0" * 32
    (src / GOOD).write_bytes(png)
    publish_release(str(src), str(tmp_path / "store"), st.version, gate_report=gates_of(src))
    # files publish would refuse, put into the release folder at rest: the server still hands out
    # nothing but previews
    release = next((tmp_path / "store").glob(f"*/{st.version}"))
    (release / "previews" / "notes.txt").write_text("not a preview type")
    (release / "secret.txt").write_text("inside the release but not under previews/")
    (tmp_path / "outside.png").write_bytes(png)

    proc = subprocess.Popen([sys.executable, "-m", "drivetrack.cli", "status", str(tmp_path / "store"),
                             "--version", st.version, "--port", "0"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline()
        m = re.search(r"http://127\.0\.0\.1:(\d+)/", line)
        assert m, (line, proc.stderr.read() if proc.poll() is not None else "")
        port = int(m.group(1))
        code, ctype, body = _raw_get(port, "/")
        assert code == 200 and ctype.startswith("text/html")
        _assert_safe(body.decode())
        code, ctype, body = _raw_get(port, f"/{GOOD}")
        assert (code, ctype, body) == (200, "image/png", png)
        for bad in ["/previews/../secret.txt", "/previews/training/../../secret.txt", "/secret.txt",
                    "/previews/%2e%2e/secret.txt", "/previews/..%2fsecret.txt", "/previews/notes.txt",
                    "/previews/../../outside.png", "/../outside.png", "/previews//etc/passwd",
                    "/manifest.json", "/previews/training/missing.png", "//evil.example/x.png",
                    "/previews/training/good_clip.png/..", "/previews\\..\\secret.txt"]:
            code, _, body = _raw_get(port, bad)
            assert code in (400, 404), (bad, code)
            assert b"inside the release" not in body and png not in body, bad
    finally:
        proc.terminate()
        proc.wait(timeout=10)


def test_quality_of_a_folder_with_a_corrupt_table_names_the_file(tmp_path):
    from drivetrack.release.status_pages import ReleaseQuality, read_quality

    (tmp_path / "stats").mkdir()
    (tmp_path / "stats" / "segments.parquet").write_bytes(b"not parquet")
    with pytest.raises(StatusError, match=r"stats/segments.parquet: not a readable parquet table"):
        read_quality(str(tmp_path))
    assert read_quality(str(tmp_path / "nothing-here")) == ReleaseQuality()


def test_a_published_status_json_that_is_not_json_is_an_error_naming_it(tmp_path):
    from drivetrack.release import publish_release
    from drivetrack.release.status import read_release_status

    from test_release import gates_of, make_output

    src = make_output(tmp_path / "src", n_clips=1)
    st = hostile_status()
    write_status(str(src), st)
    publish_release(str(src), str(tmp_path / "store"), st.version, gate_report=gates_of(src))
    published = next((tmp_path / "store").glob(f"*/{st.version}/status.json"))
    published.write_bytes(b'{"dataset": "d", "vers')   # damaged at rest
    with pytest.raises(StatusError, match=rf"{st.version}/status.json: not valid JSON"):
        read_release_status(str(tmp_path / "store"), st.version, published.parent.parent.name)
