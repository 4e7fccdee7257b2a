"""A local HTTP server that serves a directory with Range requests and counts every request
(tests and tools/bench_remote.py read archives from it over real HTTP on 127.0.0.1)."""

from __future__ import annotations

import http.server
import os
import re
import threading
from pathlib import Path

_RANGE = re.compile(r"bytes=(\d+)-(\d*)$")


class RangeServer:
    """``with RangeServer(root) as srv: srv.url("a.h5")``; ``srv.log`` lists (method, path,
    range header, bytes sent) of every request; ``delay`` seconds are slept before each answer
    (a stand-in for network latency, or a stalled server); ``redirects`` maps a request path
    (without its query) to the URL a 302 answer sends the client to."""

    def __init__(self, root: str | os.PathLike[str], delay: float = 0.0, honour_range: bool = True,
                 redirects: dict[str, str] | None = None):
        self.root = Path(root)
        self.delay = delay
        self.honour_range = honour_range
        self.redirects = dict(redirects or {})
        self.log: list[tuple[str, str, str | None, int]] = []
        self._lock = threading.Lock()
        server = self

        class Handler(http.server.BaseHTTPRequestHandler):
            protocol_version = "HTTP/1.1"

            def log_message(self, *args: object) -> None:
                pass

            def _file(self) -> Path | None:
                rel = self.path.split("?", 1)[0].lstrip("/")
                p = (server.root / rel).resolve()
                if server.root.resolve() not in p.parents or not p.is_file():
                    return None
                return p

            def _answer(self, head: bool) -> None:
                import time

                if server.delay:
                    time.sleep(server.delay)
                rng = self.headers.get("Range")
                target = server.redirects.get(self.path.split("?", 1)[0])
                if target is not None:
                    self.send_response(302)
                    self.send_header("Location", target)
                    self.send_header("Content-Length", "0")
                    self.end_headers()
                    server._record(self.command, self.path, rng, 0)
                    return
                p = self._file()
                if p is None:
                    self.send_response(404)
                    self.send_header("Content-Length", "0")
                    self.end_headers()
                    server._record(self.command, self.path, rng, 0)
                    return
                size = p.stat().st_size
                start, end = 0, size
                m = _RANGE.match(rng or "")
                partial = bool(m) and server.honour_range and not head
                if partial:
                    start = int(m.group(1))
                    end = min(size, int(m.group(2)) + 1) if m.group(2) else size
                    self.send_response(206)
                    self.send_header("Content-Range", f"bytes {start}-{end - 1}/{size}")
                else:
                    self.send_response(200)
                self.send_header("Accept-Ranges", "bytes")
                self.send_header("Content-Length", str(end - start))
                self.end_headers()
                data = b""
                if not head:
                    with open(p, "rb") as f:
                        f.seek(start)
                        data = f.read(end - start)
                # recorded before the client can see the answer, so a count taken after a read
                # returned includes it
                server._record(self.command, self.path, rng, len(data))
                try:
                    self.wfile.write(data)
                except (BrokenPipeError, ConnectionResetError):  # the client gave up (a timeout)
                    pass

            def do_GET(self) -> None:  # noqa: N802
                self._answer(head=False)

            def do_HEAD(self) -> None:  # noqa: N802
                self._answer(head=True)

        self._httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self._httpd.daemon_threads = True
        self._thread = threading.Thread(target=self._httpd.serve_forever, daemon=True)

    def _record(self, method: str, path: str, rng: str | None, sent: int) -> None:
        with self._lock:
            self.log.append((method, path, rng, sent))

    def url(self, rel: str, host: str = "127.0.0.1") -> str:
        return f"http://{host}:{self._httpd.server_address[1]}/{rel}"

    def count(self, method: str = "GET") -> int:
        with self._lock:
            return sum(1 for r in self.log if r[0] == method)

    def sent(self) -> int:
        with self._lock:
            return sum(r[3] for r in self.log)

    def reset(self) -> None:
        with self._lock:
            self.log.clear()

    def __enter__(self) -> RangeServer:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._httpd.shutdown()
        self._httpd.server_close()
