"""``drivetrack status STORE [--version V] [--port P]``: serve a release's status page.

STORE is a release store URL (the page published inside the release is served), or a local
annotation/work folder holding ``status.json`` (a build in progress: the page is re-rendered
from ``status.json`` on every request and refreshes itself)."""
from __future__ import annotations

import sys

from drivetrack.commands._release_common import (EXIT_BAD_INPUT, EXIT_CODES_HELP, add_store_options,
                                                 check_dataset_arg, run_store_command, storage_options)


def add_parser(sub) -> None:
    p = sub.add_parser("status", help="serve the per-segment status page of a release on 127.0.0.1",
                       description="Serves the self-contained status page (per segment and stage: pending, "
                                   "running, done, failed, counts, durations, errors) with http.server. "
                                   "--print prints the per-segment summary instead of serving.",
                       epilog=EXIT_CODES_HELP)
    p.add_argument("store", help="release store URL, or a folder holding status.json (a build in progress)")
    p.add_argument("--version", default="latest", dest="release_version", help="version, or 'latest' (default)")
    p.add_argument("--port", type=int, default=8765, help="port on 127.0.0.1 (0 picks a free one)")
    p.add_argument("--host", default="127.0.0.1", help="address to bind (default 127.0.0.1)")
    p.add_argument("--print", action="store_true", dest="print_only", help="print a summary, do not serve")
    add_store_options(p)
    p.set_defaults(func=run)


def _page_source(args):
    """-> (describe, get_page() -> bytes, status)"""
    import fsspec

    from drivetrack.status import STATUS_JSON, read_release_status, read_status, render_status_html

    check_dataset_arg(args)
    so = storage_options(args)
    fs, path = fsspec.core.url_to_fs(args.store, **(so or {}))
    if fs.exists(f"{path.rstrip('/')}/{STATUS_JSON}"):
        def page() -> bytes:
            return render_status_html(read_status(args.store, storage_options=so), refresh_s=5).encode()
        return f"build folder {args.store}", page, read_status(args.store, storage_options=so)
    version, html_bytes, status = read_release_status(args.store, args.release_version, args.dataset,
                                                      storage_options=so)
    return f"{args.dataset} {version} in {args.store}", (lambda: html_bytes), status


def run(args) -> int:
    import http.server
    import json

    from drivetrack.release import ReleaseError
    from drivetrack.status import StatusError

    found = []

    def load() -> int:
        found.append(_page_source(args))
        return 0

    code = run_store_command("status", args.store, load,
                             [((ReleaseError, StatusError, FileNotFoundError, ValueError), EXIT_BAD_INPUT)])
    if code:
        return code
    what, page, status = found[0]
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
            if self.path.split("?")[0] not in ("/", "/status.html", "/index.html", "/status.json"):
                self.send_error(404, "only / and /status.json are served")
                return
            try:
                if self.path.startswith("/status.json"):
                    body, ctype = json.dumps(_page_source(args)[2].to_dict(), indent=1).encode(), "application/json"
                else:
                    body, ctype = page(), "text/html; charset=utf-8"
            except Exception as e:  # a page that cannot be read is reported to the browser and the log
                self.send_error(500, f"{type(e).__name__}: {e}")
                return
            self.send_response(200)
            self.send_header("Content-Type", ctype)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Cache-Control", "no-store")
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
