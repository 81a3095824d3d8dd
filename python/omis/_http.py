"""HTTP to the coordinator with the standard library: JSON requests, uploads, downloads and
the Server-Sent Events stream (proto/openapi.yaml)."""

from __future__ import annotations

import json
import socket
import time
import urllib.error
import urllib.parse
import urllib.request
from dataclasses import dataclass
from typing import Any, Iterator, Optional

from .errors import ConnectionFailed, ServiceError

#: Seconds a request waits for the coordinator's answer (and between two reads of a stream).
DEFAULT_TIMEOUT = 60.0


@dataclass(frozen=True)
class Event:
    """One Server-Sent Event of a job: ``id`` (resume after it with Last-Event-ID), ``kind``
    (``queued``, ``tile_done``, ``pass_done``, ``preview``, ``task_failed``, ``done``,
    ``failed``, ``cancelled``) and ``data`` (the kind's fields plus ``job`` and ``at``)."""

    id: Optional[str]
    kind: str
    data: dict[str, Any]

    @property
    def terminal(self) -> bool:
        """Whether the job ends with this event."""
        return self.kind in ("done", "failed", "cancelled")


class Transport:
    """Requests to one coordinator, with its client token."""

    def __init__(self, base: str, token: Optional[str], timeout: float = DEFAULT_TIMEOUT) -> None:
        base = base.rstrip("/")
        if not base.startswith("http://"):
            raise ValueError(
                f"url '{base}' is not an http:// URL (omis speaks plain HTTP; put a TLS proxy "
                "in front of a coordinator on an untrusted network)"
            )
        self.base = base
        self.token = token
        self.timeout = timeout

    def _request(
        self,
        method: str,
        path: str,
        *,
        query: Optional[dict[str, str]] = None,
        body: Optional[bytes] = None,
        content_type: Optional[str] = None,
        headers: Optional[dict[str, str]] = None,
    ) -> urllib.request.Request:
        url = self.base + path
        if query:
            url += "?" + urllib.parse.urlencode(query)
        req = urllib.request.Request(url, data=body, method=method)
        if self.token is not None:
            req.add_header("Authorization", f"Bearer {self.token}")
        if content_type:
            req.add_header("Content-Type", content_type)
        for k, v in (headers or {}).items():
            req.add_header(k, v)
        return req

    def open(
        self,
        method: str,
        path: str,
        what: str,
        *,
        query: Optional[dict[str, str]] = None,
        body: Optional[bytes] = None,
        content_type: Optional[str] = None,
        headers: Optional[dict[str, str]] = None,
        timeout: Optional[float] = None,
    ) -> Any:
        """Sends a request; returns the open response, or raises `ServiceError` with the
        server's JSON error for a non-2xx answer."""
        req = self._request(
            method, path, query=query, body=body, content_type=content_type, headers=headers
        )
        try:
            return urllib.request.urlopen(req, timeout=timeout or self.timeout)
        except urllib.error.HTTPError as e:
            raise _service_error(e, what) from None
        except (urllib.error.URLError, OSError) as e:
            raise ConnectionFailed(f"{what}: cannot reach {self.base}: {e}") from None

    def read(self, method: str, path: str, what: str, **kw: Any) -> bytes:
        """The whole body of the answer."""
        with self.open(method, path, what, **kw) as r:
            data: bytes = r.read()
            return data

    def json(
        self, method: str, path: str, what: str, payload: Any = None, **kw: Any
    ) -> Any:
        """A JSON answer; `payload`, when given, is sent as a JSON body."""
        if payload is not None:
            kw["body"] = json.dumps(payload).encode()
            kw["content_type"] = "application/json"
        return json.loads(self.read(method, path, what, **kw))

    def events(
        self,
        path: str,
        last_event_id: Optional[str] = None,
        timeout: Optional[float] = None,
        reconnects: int = 30,
    ) -> Iterator[Event]:
        """The events of an SSE stream until a terminal one. A stream that breaks is opened
        again with Last-Event-ID (the id of the last event seen), at most `reconnects` times
        in a row without an event in between; `timeout` bounds the whole iteration."""
        deadline = None if timeout is None else time.monotonic() + timeout
        failures = 0
        while True:
            headers = {"Accept": "text/event-stream"}
            if last_event_id is not None:
                headers["Last-Event-ID"] = last_event_id
            # The server sends a comment every 15 s, so a silent minute is a dead connection.
            read_timeout = 60.0
            if deadline is not None:
                read_timeout = max(0.1, min(read_timeout, deadline - time.monotonic()))
            try:
                resp = self.open(
                    "GET", path, "following the job", headers=headers, timeout=read_timeout
                )
            except ConnectionFailed:
                failures += 1
                if failures > reconnects:
                    raise
                _check_deadline(deadline)
                time.sleep(0.5)
                continue
            try:
                for event in _parse_sse(resp, deadline):
                    failures = 0
                    if event.id is not None:
                        last_event_id = event.id
                    yield event
                    if event.terminal:
                        return
            except (socket.timeout, TimeoutError, ConnectionError, OSError):
                pass
            finally:
                resp.close()
            _check_deadline(deadline)
            failures += 1
            if failures > reconnects:
                raise ConnectionFailed(f"the event stream of {path} keeps breaking")
            time.sleep(0.2)


def _check_deadline(deadline: Optional[float]) -> None:
    if deadline is not None and time.monotonic() >= deadline:
        raise TimeoutError("the job's events did not end within the timeout")


def _parse_sse(resp: Any, deadline: Optional[float]) -> Iterator[Event]:
    """Events of one SSE response (https://html.spec.whatwg.org/#event-stream-interpretation);
    comments are skipped; an event's id is the last `id:` line seen."""
    kind = ""
    data: list[str] = []
    last_id: Optional[str] = None
    while True:
        _check_deadline(deadline)
        raw = resp.readline()
        if not raw:
            return
        line = raw.decode("utf-8", "replace").rstrip("\r\n")
        if line == "":
            if data or kind:
                text = "\n".join(data)
                try:
                    payload = json.loads(text) if text else {}
                except json.JSONDecodeError:
                    payload = {"raw": text}
                yield Event(last_id, kind or "message", payload)
            kind, data = "", []
            continue
        if line.startswith(":"):
            continue
        name, _, value = line.partition(":")
        if value.startswith(" "):
            value = value[1:]
        if name == "event":
            kind = value
        elif name == "data":
            data.append(value)
        elif name == "id":
            last_id = value


def _service_error(e: urllib.error.HTTPError, what: str) -> ServiceError:
    try:
        text = e.read().decode("utf-8", "replace")
    except OSError:
        text = ""
    body: Any = None
    message = text or (e.reason if isinstance(e.reason, str) else str(e.reason))
    field = None
    try:
        body = json.loads(text)
        if isinstance(body, dict) and isinstance(body.get("error"), str):
            message = body["error"]
            f = body.get("field")
            field = f if isinstance(f, str) else None
    except json.JSONDecodeError:
        pass
    return ServiceError(e.code, message, field, body, what)
