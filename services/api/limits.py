"""Request-body size limit enforced while the body streams in, before anything is parsed or stored."""

from __future__ import annotations

import json

TOO_LARGE = "kneemesh.too_large"


class _TooLarge(Exception):
    pass


class BodySizeLimit:
    """ASGI middleware: 413 for a body over ``limit`` bytes (by Content-Length, or counted as it arrives).

    A body that overruns while the form is being parsed surfaces inside the
    framework as a parse error; the scope flag ``kneemesh.too_large`` lets the
    error handler answer 413 for it.
    """

    def __init__(self, app, limit: int):
        self.app = app
        self.limit = limit

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http" or scope["method"] not in ("POST", "PUT"):
            return await self.app(scope, receive, send)
        length = dict(scope["headers"]).get(b"content-length")
        if length is not None and length.isdigit() and int(length) > self.limit:
            return await self._reject(send)
        seen = 0
        started = False

        async def counted():
            nonlocal seen
            message = await receive()
            seen += len(message.get("body", b""))
            if seen > self.limit:
                scope[TOO_LARGE] = True
                raise _TooLarge()
            return message

        async def tracked(message):
            nonlocal started
            started = started or message["type"] == "http.response.start"
            await send(message)

        try:
            await self.app(scope, counted, tracked)
        except _TooLarge:
            if not started:
                await self._reject(send)

    async def _reject(self, send):
        body = json.dumps({"code": "upload_too_large",
                           "message": f"the upload is larger than this server's limit of {self.limit} bytes; "
                                      "send a smaller file or ask the operator to raise KNEEMESH_MAX_UPLOAD_BYTES."}).encode()
        await send({"type": "http.response.start", "status": 413,
                    "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]})
        await send({"type": "http.response.body", "body": body})
