"""The HTTP edge: request-size limit, early answers that do not reset the connection, HEAD, and 500s.

`BodyLimitMiddleware`: a body larger than the limit is refused with 413 without being buffered. A declared
Content-Length above the limit is refused before the app runs; a chunked body is counted as it streams and
fails with 413 as soon as the count passes the limit.

Whatever answers a request before its body is read (that 413, a 401, a 404 on a POST), the rest of the body is
read and thrown away before the answer goes out, up to `drain_bytes` (and `DRAIN_SECONDS`): a client that
sends its body without `Expect: 100-continue` (Python's urllib, many PLC and cell-PC HTTP stacks) is still
writing it, and closing a socket with unread data makes the kernel reset the connection, so the client would
see "connection reset" instead of the answer. The connection then stays open (keep-alive).

A body beyond that bound (issue 33: a 90 MB upload reached http.client and urllib as BrokenPipe, not the 413)
gets a lingering close, as nginx's: the whole answer is sent at once with `Connection: close`, then the rest of
the body is read and thrown away, up to `linger_bytes` (16x the limit, at least 256 MiB), `LINGER_SECONDS` in all
and `LINGER_IDLE_SECONDS` without a byte, and only then is the connection closed. A client that reads while it
sends (curl) stops at the answer; one that sends first reads it once its body is gone. Beyond those bounds the
client may see a reset. A client that waits for `100 Continue` is answered at once, and nothing is read.

`HeadMiddleware`: HEAD on any GET route answers like GET (status, headers, Content-Length) without a body.

`InternalErrorMiddleware`: an unexpected exception becomes the app's 500 problem document with
`Connection: close`, so a keep-alive client is told the connection ends instead of finding it dropped.

`BatchLimitMiddleware`: `POST /calibrations/{id}/predict` and `.../compensate` take at most MAX_PREDICT_BYTES
and MAX_PREDICT_ROWS rows, refused with 413 before FastAPI parses the JSON and pydantic validates it: both run
on the event loop (FastAPI parses a JSON body there whatever the route), and 100k rows of `"x"` cost 0.1-0.4 s
of pydantic errors there, during which nothing else, /health included, is answered (issue 10, the red team's
load). The rows are counted from the bytes (`largest_container`, vectorised, in a thread of its own limiter:
numpy lets the event loop run meanwhile, where `json.loads` would hold the GIL as long as it parses).
"""
from __future__ import annotations

import asyncio
import json
import re
import time
from dataclasses import dataclass
from typing import Awaitable, Callable

import anyio
import anyio.to_thread
import numpy as np
from starlette.exceptions import HTTPException
from starlette.requests import Request
from starlette.responses import Response
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from .problems import problem_response

DRAIN_SECONDS = 30.0
"""At most this long is spent reading and discarding a refused request's body."""
MIN_DRAIN_BYTES = 64 * 1024 * 1024
LINGER_SECONDS = 30.0
"""A lingering close reads and discards at most this long after the answer was sent (nginx's lingering_time)."""
LINGER_IDLE_SECONDS = 5.0
"""... and stops when the client sends nothing for this long (nginx's lingering_timeout)."""
MIN_LINGER_BYTES = 256 * 1024 * 1024
CLOSE = (b"connection", b"close")

MAX_PREDICT_ROWS = 10_000
"""At most this many rows (poses, targets: the items of `joints`, `targets`, `seed_joints`, `program_joints`,
and per-pose `payload`, `temperature`, `timestamp`) in one predict or compensate request, and at most this many
items in any list or object of its body. More: 413 naming the field, its count and this maximum, before the
JSON is parsed (`BatchLimitMiddleware`); send the rest in further requests. 10 000 poses are predicted in well
under a second; the request schemas (calibrations/schemas.py MAX_POSES) say the same maximum."""
MAX_PREDICT_BYTES = 4 * 1024 * 1024
"""At most this many bytes in the body of one predict or compensate request (413 above it, before it is read):
10 000 rows of a 12-joint robot with their targets at full precision take about 3 MB. Bounds the JSON parse
FastAPI does on the event loop for a request that passes the row count (about 0.1 s for 4 MiB)."""
BATCH_PATH = re.compile(r"/calibrations/[^/]+/(predict|compensate)/?$")
"""The routes `BatchLimitMiddleware` guards (POST)."""


def header(scope: Scope, name: bytes) -> bytes | None:
    """The first value of a request header (`name` in lower case), as sent."""
    for k, v in scope.get("headers", ()):
        if k == name:
            return v
    return None


def _with_close(msg: Message) -> Message:
    headers = [(k, v) for k, v in msg.get("headers", []) if k != b"connection"]
    return {**msg, "headers": [*headers, CLOSE]}


class BodyLimitMiddleware:
    def __init__(self, app: ASGIApp, max_bytes: int, drain_bytes: int | None = None, linger_bytes: int | None = None):
        self.app, self.max_bytes = app, max_bytes
        self.drain_bytes = max(4 * max_bytes, MIN_DRAIN_BYTES) if drain_bytes is None else drain_bytes
        self.linger_bytes = max(16 * max_bytes, MIN_LINGER_BYTES) if linger_bytes is None else linger_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        limit = self.max_bytes
        cl = header(scope, b"content-length")
        try:
            declared = int(cl) if cl is not None else None
        except ValueError:
            declared = None  # the server rejects it before we run
        chunked = b"chunked" in (header(scope, b"transfer-encoding") or b"").lower()
        waits_for_continue = (header(scope, b"expect") or b"").lower() == b"100-continue"
        state = {"seen": 0, "done": not (chunked or (declared or 0) > 0), "asked": False}

        async def drain(max_bytes: int | None = None, seconds: float = DRAIN_SECONDS,
                        idle: float | None = None) -> bool:
            """Read and discard the rest of the body (at most max_bytes in all, default drain_bytes, and `seconds`,
            or `idle` seconds without a byte); True when all of it was read."""
            if state["done"]:
                return True
            if waits_for_continue and not state["asked"]:
                return False  # the client has not sent it and will not unless asked
            max_bytes = self.drain_bytes if max_bytes is None else max_bytes
            if declared is not None and declared > max_bytes:
                return False
            deadline = time.monotonic() + seconds
            while state["seen"] <= max_bytes:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                try:
                    msg = await asyncio.wait_for(receive(), left if idle is None else min(left, idle))
                except asyncio.TimeoutError:
                    return False
                if msg["type"] != "http.request":
                    state["done"] = True  # disconnected: nothing left to read
                    return True
                state["seen"] += len(msg.get("body", b""))
                if not msg.get("more_body", False):
                    state["done"] = True
                    return True
            return False

        async def linger() -> None:
            """After the whole answer went out: read and discard what the client still sends (bounded)."""
            if not state["done"] and not (waits_for_continue and not state["asked"]):
                await drain(self.linger_bytes + state["seen"], LINGER_SECONDS, LINGER_IDLE_SECONDS)

        if declared is not None and declared > limit:
            response = problem_response(Request(scope), 413, f"the request body ({declared} bytes) exceeds the "
                                        f"limit of {limit} bytes", kind="too-large")
            await self._answer(response, drain, linger, scope, receive, send)
            return

        started = False
        lingering = False

        async def limited_receive() -> Message:
            state["asked"] = True
            msg = await receive()
            if msg["type"] == "http.request":
                state["seen"] += len(msg.get("body", b""))
                if not msg.get("more_body", False):
                    state["done"] = True
                if state["seen"] > limit:
                    raise HTTPException(413, f"the request body exceeds the limit of {limit} bytes")
            else:
                state["done"] = True
            return msg

        async def guarded_send(msg: Message) -> None:
            nonlocal started, lingering
            if msg["type"] == "http.response.start":
                started = True
                if not state["done"] and not await drain():
                    msg, lingering = _with_close(msg), True
            elif lingering and msg["type"] == "http.response.body" and not msg.get("more_body", False):
                # the answer's last bytes go out now, the end of the response (and the close) after the linger
                await send({**msg, "more_body": True})
                await linger()
                msg = {"type": "http.response.body", "body": b"", "more_body": False}
            await send(msg)

        try:
            await self.app(scope, limited_receive, guarded_send)
        except HTTPException as exc:  # raised outside the routes' exception handling
            if exc.status_code != 413 or started:
                raise
            await self._answer(problem_response(Request(scope), 413, exc.detail, kind="too-large"),
                               drain, linger, scope, receive, send)

    @staticmethod
    async def _answer(response: Response, drain: Callable[[], Awaitable[bool]], linger: Callable[[], Awaitable[None]],
                      scope: Scope, receive: Receive, send: Send) -> None:
        """An answer given before the body was read: the body drained first (keep-alive), or a lingering close."""
        if await drain():
            await response(scope, receive, send)
            return
        response.headers["Connection"] = "close"
        await send({"type": "http.response.start", "status": response.status_code,
                    "headers": response.raw_headers})
        await send({"type": "http.response.body", "body": response.body, "more_body": True})
        await linger()
        await send({"type": "http.response.body", "body": b"", "more_body": False})


class HeadMiddleware:
    """HEAD is GET without the body (RFC 9110 9.3.2): routed as GET, the body dropped, the headers kept."""

    def __init__(self, app: ASGIApp):
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["method"] != "HEAD":
            await self.app(scope, receive, send)
            return

        async def send_headers_only(msg: Message) -> None:
            if msg["type"] == "http.response.body":
                msg = {**msg, "body": b""}
            await send(msg)

        await self.app({**scope, "method": "GET"}, receive, send_headers_only)


class InternalErrorMiddleware:
    """An unexpected exception: the app's own 500 answer (`handler`, the problem document) with
    `Connection: close`; the exception is not passed on to the server (which would drop the connection
    without a word). If the answer had already started, nothing can be said: the exception goes on."""

    def __init__(self, app: ASGIApp, handler: Callable[[Request, Exception], Awaitable[Response]]):
        self.app, self.handler = app, handler

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        started = False

        async def tracking_send(msg: Message) -> None:
            nonlocal started
            if msg["type"] == "http.response.start":
                started = True
            await send(msg)

        try:
            await self.app(scope, receive, tracking_send)
        except HTTPException:
            raise  # BodyLimitMiddleware's own 413, raised from the body stream
        except Exception as exc:
            if started:
                raise
            response = await self.handler(Request(scope), exc)
            response.headers["Connection"] = "close"
            await response(scope, receive, send)


@dataclass(frozen=True)
class Largest:
    """The JSON array or object of a body that holds the most items (`largest_container`)."""
    items: int
    depth: int  # 1: the body itself, 2: the value of a top-level member, 3: an item of that value, ...
    field: str | None  # the top-level member it is in (None at depth 1 or when it cannot be told)


_KEY = re.compile(rb'\s*"((?:[^"\\]|\\.){0,200})"\s*:')


def largest_container(body: bytes) -> Largest:
    """The container (array or object) of the JSON text `body` with the most items, counted from the bytes
    without parsing: the commas outside strings (a quote after an odd run of backslashes is escaped), each
    given to the innermost container around it. Linear, vectorised (numpy releases the GIL for most of it);
    about 10 ms a megabyte. A body that is not JSON gives some count: the parser refuses it later anyway."""
    a = np.frombuffer(body, dtype=np.uint8)
    quote = a == 0x22
    bs = np.flatnonzero(a == 0x5C)
    if bs.size:
        starts = np.flatnonzero(np.diff(bs, prepend=-2) != 1)  # runs of backslashes
        ends = np.append(starts[1:], bs.size) - 1
        after = bs[ends[(ends - starts) % 2 == 0]] + 1  # right after a run of odd length: escaped
        quote[after[after < a.size]] = False
    outside = ~np.logical_xor.accumulate(quote)  # structural characters are outside strings
    pos = np.flatnonzero(((a == 0x5B) | (a == 0x7B) | (a == 0x5D) | (a == 0x7D) | (a == 0x2C)) & outside)
    if not pos.size:
        return Largest(0, 0, None)
    ch = a[pos]
    opens = (ch == 0x5B) | (ch == 0x7B)
    closes = (ch == 0x5D) | (ch == 0x7D)
    depth = np.cumsum(opens.astype(np.int32) - closes.astype(np.int32))  # after the character
    keep = ~closes
    pos, depth, opens = pos[keep], np.clip(depth[keep], -1, 30000).astype(np.int16), opens[keep]
    # a comma belongs to the last container opened before it at its own depth: group by depth (stable, so
    # each group stays in text order) and carry the index of the last opening forward
    order = np.argsort(depth, kind="stable")
    pos, depth, opens = pos[order], depth[order], opens[order]
    last = np.maximum.accumulate(np.where(opens, np.arange(pos.size), -1))
    commas = np.flatnonzero(~opens)
    owner = last[commas]
    ok = owner >= 0
    commas, owner = commas[ok], owner[ok]
    owner = owner[depth[owner] == depth[commas]]
    if not owner.size:
        return Largest(int(opens.any()), 1, None)
    counts = np.bincount(owner, minlength=pos.size)
    k = int(counts.argmax())
    items, d, at = int(counts[k]) + 1, int(depth[k]), int(pos[k])
    field = None
    if d >= 2:  # the top-level member it is in starts after the last depth-1 comma (or the opening brace)
        top = (depth == 1) & (pos < at)
        start = int(pos[top].max()) if top.any() else -1
        m = _KEY.match(body, start + 1) if start >= 0 and body[start] in b",{" else None
        if m:
            try:
                field = str(json.loads(b'"' + m.group(1) + b'"'))[:64]
            except ValueError:
                field = None
    return Largest(items, d, field)


class BatchLimitMiddleware:
    """POST predict / compensate (`BATCH_PATH`): a body over `max_bytes` (declared, or counted as it streams)
    or with a list or object of more than `max_rows` items is refused with 413 (problem document naming the
    field, its count and the maximum: `field`, `items`, `max_rows`) before the app parses it. A body that
    passes is handed on unchanged. Sits inside `BodyLimitMiddleware`, which reads away what is left of a
    refused body."""

    def __init__(self, app: ASGIApp, max_rows: int = MAX_PREDICT_ROWS, max_bytes: int = MAX_PREDICT_BYTES,
                 scan_threads: int = 2):
        self.app, self.max_rows, self.max_bytes = app, max_rows, max_bytes
        self.limiter = anyio.CapacityLimiter(scan_threads)  # its own: never waits behind the route threads

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["method"] != "POST" or not BATCH_PATH.search(scope["path"]):
            await self.app(scope, receive, send)
            return
        cl = header(scope, b"content-length")
        declared = int(cl) if cl is not None and cl.isdigit() else None
        if declared is not None and declared > self.max_bytes:
            await self._too_large(scope, receive, send, f"the request body ({declared} bytes) exceeds the limit of "
                                  f"{self.max_bytes} bytes of a predict or compensate request ({self.max_rows} "
                                  "rows at most): send it in several requests", items=None, field=None)
            return
        chunks, size, more = [], 0, True
        while more:
            msg = await receive()
            if msg["type"] != "http.request":
                return  # the client went away
            chunk = msg.get("body", b"")
            size += len(chunk)
            more = msg.get("more_body", False)
            if size > self.max_bytes:
                await self._too_large(scope, receive, send, f"the request body exceeds the limit of {self.max_bytes} "
                                      f"bytes of a predict or compensate request ({self.max_rows} rows at most): "
                                      "send it in several requests", items=None, field=None)
                return
            chunks.append(chunk)
        body = b"".join(chunks)
        if body.count(b",") >= self.max_rows:  # fewer commas: no list or object can hold more items
            big = await anyio.to_thread.run_sync(largest_container, body, limiter=self.limiter)
            if big.items > self.max_rows:
                where = "the request body" if big.depth <= 1 or big.field is None else f"`{big.field}`"
                what = "rows" if big.depth == 2 else "items in one list or object"
                await self._too_large(scope, receive, send, f"{where} has {big.items} {what}; a predict or compensate "
                                      f"request takes at most {self.max_rows}: send them in several requests",
                                      items=big.items, field=None if big.field is None else f"body.{big.field}")
                return
        sent = False

        async def replay() -> Message:
            nonlocal sent
            if not sent:
                sent = True
                return {"type": "http.request", "body": body, "more_body": False}
            return await receive()

        await self.app(scope, replay, send)

    async def _too_large(self, scope: Scope, receive: Receive, send: Send, detail: str, items: int | None,
                         field: str | None) -> None:
        extra = {"max_rows": self.max_rows, "max_bytes": self.max_bytes}
        if items is not None:
            extra["items"] = items
        if field is not None:
            extra["field"] = field
        await problem_response(Request(scope), 413, detail, kind="too-large", **extra)(scope, receive, send)
