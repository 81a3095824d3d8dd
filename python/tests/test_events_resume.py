"""A broken event stream is resumed with Last-Event-ID: a stand-in server that cuts the stream
after two events, then answers the resumed request with the rest."""

from __future__ import annotations

import http.server
import json
import threading
from typing import Iterator

import pytest

import omis

EVENTS = [
    (11, "queued", {"width": 2, "height": 2, "spp": 2}),
    (12, "tile_done", {"pass": 0, "tile": 0, "worker": "w", "bytes": 10}),
    (15, "pass_done", {"pass": 0, "spp": 1, "seconds": 0.1, "relmse": None}),
    (19, "done", {"spp": 2}),
]


class Handler(http.server.BaseHTTPRequestHandler):
    seen: list[str | None] = []

    def log_message(self, *args: object) -> None:
        pass

    def do_GET(self) -> None:
        last = self.headers.get("Last-Event-ID")
        Handler.seen.append(last)
        after = int(last) if last else 0
        todo = [e for e in EVENTS if e[0] > after]
        if last is None:
            todo = todo[:2]  # the first connection breaks after two events
        self.send_response(200)
        self.send_header("Content-Type", "text/event-stream")
        self.end_headers()
        self.wfile.write(b": keep-alive comment\n\n")
        for i, kind, data in todo:
            body = json.dumps({**data, "job": "j", "at": 1.0})
            self.wfile.write(f"id: {i}\nevent: {kind}\ndata: {body}\n\n".encode())
        self.wfile.flush()
        self.close_connection = True


@pytest.fixture
def server() -> Iterator[str]:
    Handler.seen = []
    httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    t = threading.Thread(target=httpd.serve_forever, daemon=True)
    t.start()
    try:
        yield f"http://127.0.0.1:{httpd.server_address[1]}"
    finally:
        httpd.shutdown()
        httpd.server_close()


def test_stream_resumes_after_the_last_event(server: str) -> None:
    job = omis.Job(omis.Client(server), "j")
    events = list(job.events(timeout=30))
    assert [(int(e.id or 0), e.kind) for e in events] == [(i, k) for i, k, _ in EVENTS]
    assert events[-1].terminal and events[2].data["spp"] == 1
    assert Handler.seen == [None, "12"]
