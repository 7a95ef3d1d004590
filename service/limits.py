"""Streaming request-size limit: a body larger than the limit is refused with 413 without being buffered.

A declared Content-Length above the limit is refused before a byte is read; a chunked body is counted as it
streams and the request fails with 413 as soon as the count passes the limit.
"""
from __future__ import annotations

from starlette.exceptions import HTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from .problems import problem_response


class BodyLimitMiddleware:
    def __init__(self, app: ASGIApp, max_bytes: int):
        self.app, self.max_bytes = app, max_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        limit = self.max_bytes
        for k, v in scope.get("headers", []):
            if k == b"content-length":
                try:
                    declared = int(v)
                except ValueError:
                    declared = -1
                if declared > limit:
                    await problem_response(None, 413, f"the request body ({declared} bytes) exceeds the limit of "
                                           f"{limit} bytes", kind="too-large",
                                           headers={"Connection": "close"})(scope, receive, send)
                    return
        seen = 0
        started = False

        async def limited_receive() -> Message:
            nonlocal seen
            msg = await receive()
            if msg["type"] == "http.request":
                seen += len(msg.get("body", b""))
                if seen > limit:
                    raise HTTPException(413, f"the request body exceeds the limit of {limit} bytes")
            return msg

        async def tracking_send(msg: Message) -> None:
            nonlocal started
            if msg["type"] == "http.response.start":
                started = True
            await send(msg)

        try:
            await self.app(scope, limited_receive, tracking_send)
        except HTTPException as exc:  # raised outside the routes' exception handling
            if exc.status_code != 413 or started:
                raise
            await problem_response(None, 413, exc.detail, kind="too-large",
                                   headers={"Connection": "close"})(scope, receive, send)
