"""``drivetrack status STORE [--version V] [--port P]``: serve a release's status page.

STORE is a release store URL, or a local annotation/work folder holding ``status.json`` (a build
in progress: the page is re-rendered from ``status.json`` on every request and refreshes itself).
With ``--version`` the page of that version is served at ``/``; without it ``/`` is an index of
the published versions (date, segments, gate outcome, size, change from the previous version)
and each version's page is at ``/<version>/``. A page is always rendered from ``status.json`` and
the release's ``stats/*.parquet`` and ``validation/gates.json`` (quality beside state), and its
preview images are served from the release's ``previews/`` folder only."""
from __future__ import annotations

import sys

from drivetrack.commands._release_common import (EXIT_BAD_INPUT, EXIT_CODES_HELP, add_store_options,
                                                 check_dataset_arg, run_store_command, storage_options)


def add_parser(sub) -> None:
    p = sub.add_parser("status", help="serve the status page of a release (or an index of all versions) on 127.0.0.1",
                       description="Serves the self-contained status page (per segment: the state of each stage, "
                                   "counts, durations, errors, and its quality: clips, tracks, speed-error p50, "
                                   "refined share, rejected clips by reason, failing gates) and its previews with "
                                   "http.server. Without --version, / is an index of the published versions "
                                   "linking each version's page. --print prints the per-segment summary instead "
                                   "of serving.",
                       epilog=EXIT_CODES_HELP)
    p.add_argument("store", help="release store URL, or a folder holding status.json (a build in progress)")
    p.add_argument("--version", default=None, dest="release_version",
                   help="version, or 'latest'; default: serve the index of versions (--print/--json: latest)")
    p.add_argument("--port", type=int, default=8765, help="port on 127.0.0.1 (0 picks a free one)")
    p.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1)")
    p.add_argument("--print", action="store_true", dest="print_only", help="print a summary, do not serve")
    add_store_options(p)
    p.set_defaults(func=run)


class NotFound(LookupError):
    """A path the server does not serve; the message says why."""


def _content_type(rel: str) -> str:
    from drivetrack.release.status_pages import PREVIEW_TYPES

    return PREVIEW_TYPES["." + rel.rsplit(".", 1)[-1].lower()]


def _preview_rel(rel: str) -> str:
    """``rel`` when it names a preview file (under previews/, known suffix, no traversal)."""
    from drivetrack.release.status_pages import PREVIEW_TYPES, safe_release_href

    ok = safe_release_href(rel, under="previews")
    if ok is None or "." not in ok or "." + ok.rsplit(".", 1)[-1].lower() not in PREVIEW_TYPES:
        raise NotFound(f"{rel!r} is not a preview file of the release (only previews/*.png|jpg|gif|webp|mp4|webm)")
    return ok


class _BuildFolder:
    """A build in progress: ``status.json`` (and once assembled, stats) in a local or fsspec folder."""

    def __init__(self, url: str, so: dict | None):
        self.url, self.so = url.rstrip("/"), so

    def status(self):
        from drivetrack.release.status import read_status

        return read_status(self.url, storage_options=self.so)

    def get(self, path: str) -> tuple[bytes, str]:
        import json

        import fsspec

        from drivetrack.release.status_pages import read_quality, render_status_html

        if path in ("", "status.html", "index.html"):
            return render_status_html(self.status(), refresh_s=5,
                                      quality=read_quality(self.url, storage_options=self.so)).encode(), "text/html"
        if path == "status.json":
            return json.dumps(self.status().to_dict(), indent=1).encode(), "application/json"
        rel = _preview_rel(path)
        fs, root = fsspec.core.url_to_fs(self.url, **(self.so or {}))
        try:
            return fs.cat_file(f"{root.rstrip('/')}/{rel}"), _content_type(rel)
        except FileNotFoundError:
            raise NotFound(f"{rel} does not exist in {self.url}") from None


class _Release:
    """A published version: its page rendered from status.json plus its quality tables."""

    def __init__(self, store_url: str, version: str, dataset: str, so: dict | None):
        from drivetrack.release.status import read_release_status

        self.store_url, self.dataset, self.so = store_url, dataset, so
        self.version, _, self._status = read_release_status(store_url, version, dataset, storage_options=so)

    def status(self):
        return self._status

    def get(self, path: str) -> tuple[bytes, str]:
        import json

        from drivetrack.release import open_store
        from drivetrack.release.status_pages import read_quality, render_status_html

        store = open_store(self.store_url, self.so)
        if path in ("", "status.html", "index.html"):
            quality = read_quality(store.url_of(f"{self.dataset}/{self.version}"), storage_options=self.so)
            return render_status_html(self._status, quality=quality).encode(), "text/html"
        if path == "status.json":
            return json.dumps(self._status.to_dict(), indent=1).encode(), "application/json"
        rel = _preview_rel(path)
        try:
            return store.read_bytes(f"{self.dataset}/{self.version}/{rel}"), _content_type(rel)
        except FileNotFoundError:
            raise NotFound(f"{rel} is not in {self.dataset} {self.version}") from None


def index_rows(store_url: str, dataset: str, so: dict | None) -> list[dict]:
    """One row per published version, newest first: date, segments done/failed, gate outcome,
    size, and the change from the previous version (``diff_versions``). A version whose manifest
    cannot be read is listed with its error."""
    from drivetrack.release import list_versions
    from drivetrack.release.catalog import diff_versions, read_manifest

    versions = list_versions(store_url, dataset, storage_options=so)
    rows, previous = [], None
    for v in versions:
        row = {"version": v["version"], "created": v.get("created"), "bytes": v.get("bytes"),
               "files": v.get("files"), "latest": v.get("latest")}
        try:
            m = read_manifest(store_url, v["version"], dataset, storage_options=so)
            segs = [s for s in m.get("segments") or [] if isinstance(s, dict)]
            row["segments_done"] = sum(1 for s in segs if s.get("status") == "done")
            row["segments_failed"] = sum(1 for s in segs if s.get("status") == "failed")
            g = m.get("gates") if isinstance(m.get("gates"), dict) else None
            row["gates"] = None if g is None else "passed" if g.get("success") else (
                "accepted" if g.get("accepted_failure_reason") else "FAILED")
            if previous is not None:
                d = diff_versions(store_url, previous, v["version"], dataset, storage_options=so)
                deltas = sorted(d.deltas.items(), key=lambda kv: ("clips" not in kv[0], kv[0]))
                shown = [f"{k.split('.', 1)[-1]} {x['delta']:+g}" for k, x in deltas
                         if isinstance(x.get("delta"), (int, float)) and not k.endswith("bytes")][:3]
                row["diff"] = (f"from {previous}: +{len(d.added)} / -{len(d.removed)} / ~{len(d.changed)} files"
                               + (f"; {', '.join(shown)}" if shown else ""))
            else:
                row["diff"] = "first version"
        except Exception as e:  # noqa: BLE001 - one unreadable version must not hide the others
            row["error"] = f"{type(e).__name__}: {e}"
        previous = v["version"]
        rows.append(row)
    return rows[::-1]


class _Index:
    """``/`` lists the versions; ``/<version>/...`` is that version's page, json and previews."""

    def __init__(self, store_url: str, dataset: str, so: dict | None):
        self.store_url, self.dataset, self.so = store_url, dataset, so

    def get(self, path: str) -> tuple[bytes, str]:
        from drivetrack.release.manifest import SemVer
        from drivetrack.release.status_pages import render_index_html

        if path in ("", "index.html"):
            return render_index_html(self.dataset, self.store_url,
                                     index_rows(self.store_url, self.dataset, self.so)).encode(), "text/html"
        version, _, rest = path.partition("/")
        try:
            SemVer.parse(version)
        except ValueError:
            raise NotFound(f"{version!r} is not a version") from None
        return _Release(self.store_url, version, self.dataset, self.so).get(rest)


def _source(args):
    """-> (describe, site with .get(path)); raises the store's errors for an unknown version."""
    import fsspec

    from drivetrack.release.status import STATUS_JSON

    check_dataset_arg(args)
    so = storage_options(args)
    fs, path = fsspec.core.url_to_fs(args.store, **(so or {}))
    if fs.exists(f"{path.rstrip('/')}/{STATUS_JSON}"):
        return f"build folder {args.store}", _BuildFolder(args.store, so)
    if args.release_version is None and not (args.print_only or args.json):
        index_rows(args.store, args.dataset, so)  # an unreadable store fails here, not in the browser
        return f"the versions of {args.dataset} in {args.store}", _Index(args.store, args.dataset, so)
    site = _Release(args.store, args.release_version or "latest", args.dataset, so)
    return f"{args.dataset} {site.version} in {args.store}", site


def run(args) -> int:
    import http.server
    import json

    from drivetrack.release import ReleaseError
    from drivetrack.release.status import StatusError

    found = []

    def load() -> int:
        found.append(_source(args))
        return 0

    code = run_store_command("status", args.store, load,
                             [((ReleaseError, StatusError, FileNotFoundError, ValueError), EXIT_BAD_INPUT)])
    if code:
        return code
    what, site = found[0]
    if args.json or args.print_only:
        status = site.status()
    if args.json:
        print(json.dumps(status.to_dict(), indent=1))
        return 0
    if args.print_only:
        c = status.counts()
        print(f"{what}: {status.state}, {'published' if status.published else 'not published'}; "
              + ", ".join(f"{k} {v}" for k, v in c.items()))
        for row in status.table_rows():
            print(f"  {row['state']:8s} {row['split']}/{row['segment']}  {row['seconds']:.2f} s  {row['error']}")
        return 0

    class Handler(http.server.BaseHTTPRequestHandler):
        def do_GET(self):  # noqa: N802 (http.server's name)
            path = self.path.split("?", 1)[0].split("#", 1)[0]
            if not path.startswith("/"):
                self.send_error(400, "request path must start with /")
                return
            path = path[1:]
            if isinstance(site, _Index) and path and "/" not in path:
                self.send_response(301)  # /1.2.3 -> /1.2.3/ so that the page's relative links resolve
                self.send_header("Location", f"/{path}/")
                self.send_header("Content-Length", "0")
                self.end_headers()
                return
            try:
                body, ctype = site.get(path)
            except NotFound as e:
                self.send_error(404, str(e))
                return
            except (ReleaseError, FileNotFoundError) as e:
                self.send_error(404, f"{type(e).__name__}: {e}")
                return
            except Exception as e:  # a page that cannot be read is reported to the browser and the log
                self.send_error(500, f"{type(e).__name__}: {e}")
                return
            self.send_response(200)
            self.send_header("Content-Type", ctype + ("; charset=utf-8" if ctype.startswith("text/") else ""))
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Cache-Control", "no-store")
            self.send_header("X-Content-Type-Options", "nosniff")
            self.send_header("Content-Security-Policy", "default-src 'none'; img-src 'self'; media-src 'self'; "
                                                        "style-src 'unsafe-inline'")
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, fmt, *a):  # quiet: one line per request on stderr
            sys.stderr.write(f"{self.address_string()} {fmt % a}\n")

    try:
        server = http.server.ThreadingHTTPServer((args.host, args.port), Handler)
    except OSError as e:
        print(f"drivetrack status: cannot listen on {args.host}:{args.port}: {e}", file=sys.stderr)
        return 2
    host, port = server.server_address[:2]
    print(f"serving the status of {what} at http://{host}:{port}/ (Ctrl-C to stop)", flush=True)
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        pass
    finally:
        server.server_close()
    return 0
