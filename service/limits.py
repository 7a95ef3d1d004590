"""The HTTP edge: request-size limit, early answers that do not reset the connection, HEAD, and 500s.

`BodyLimitMiddleware`: a body larger than the limit is refused with 413 without being buffered. A declared
Content-Length above the limit is refused before the app runs; a chunked body is counted as it streams and
fails with 413 as soon as the count passes the limit.

Whatever answers a request before its body is read (that 413, a 401, a 404 on a POST), the rest of the body is
read and thrown away before the answer goes out, up to `drain_bytes` (and `DRAIN_SECONDS`): a client that
sends its body without `Expect: 100-continue` (Python's urllib, many PLC and cell-PC HTTP stacks) is still
writing it, and closing a socket with unread data makes the kernel reset the connection, so the client would
see "connection reset" instead of the answer. A body beyond that bound is not read: the answer is sent with
`Connection: close` (the client may then see a reset). A client that waits for `100 Continue` is answered at
once, and nothing is read.

`HeadMiddleware`: HEAD on any GET route answers like GET (status, headers, Content-Length) without a body.

`InternalErrorMiddleware`: an unexpected exception becomes the app's 500 problem document with
`Connection: close`, so a keep-alive client is told the connection ends instead of finding it dropped.
"""
from __future__ import annotations

import asyncio
import time
from typing import Awaitable, Callable

from starlette.exceptions import HTTPException
from starlette.requests import Request
from starlette.responses import Response
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from .problems import problem_response

DRAIN_SECONDS = 30.0
"""At most this long is spent reading and discarding a refused request's body."""
MIN_DRAIN_BYTES = 64 * 1024 * 1024
CLOSE = (b"connection", b"close")


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
    def __init__(self, app: ASGIApp, max_bytes: int, drain_bytes: int | None = None):
        self.app, self.max_bytes = app, max_bytes
        self.drain_bytes = max(4 * max_bytes, MIN_DRAIN_BYTES) if drain_bytes is None else drain_bytes

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

        async def drain() -> bool:
            """Read and discard the rest of the body; True when all of it was read."""
            if state["done"]:
                return True
            if waits_for_continue and not state["asked"]:
                return False  # the client has not sent it and will not unless asked
            if declared is not None and declared > self.drain_bytes:
                return False
            deadline = time.monotonic() + DRAIN_SECONDS
            while state["seen"] <= self.drain_bytes:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                try:
                    msg = await asyncio.wait_for(receive(), left)
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

        if declared is not None and declared > limit:
            response = problem_response(Request(scope), 413, f"the request body ({declared} bytes) exceeds the "
                                        f"limit of {limit} bytes", kind="too-large")
            await self._answer(response, drain, scope, receive, send)
            return

        started = False

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
            nonlocal started
            if msg["type"] == "http.response.start":
                started = True
                if not state["done"] and not await drain():
                    msg = _with_close(msg)
            await send(msg)

        try:
            await self.app(scope, limited_receive, guarded_send)
        except HTTPException as exc:  # raised outside the routes' exception handling
            if exc.status_code != 413 or started:
                raise
            await self._answer(problem_response(Request(scope), 413, exc.detail, kind="too-large"),
                               drain, scope, receive, send)

    @staticmethod
    async def _answer(response: Response, drain: Callable[[], Awaitable[bool]], scope: Scope, receive: Receive,
                      send: Send) -> None:
        if not await drain():
            response.headers["Connection"] = "close"
        await response(scope, receive, send)


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
