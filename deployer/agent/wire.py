"""A request aiohttp cannot even parse (not HTTP, a header too large) answered in the API's JSON error shape,
said on one line of the agent's log, never with a traceback (aiohttp's default answers text/plain and logs
the exception's traceback)."""

from __future__ import annotations

import sys
from http import HTTPStatus
from typing import Any

from aiohttp import web
from aiohttp.web_protocol import RequestHandler
from aiohttp.web_request import BaseRequest


def _body(status: int, message: str) -> dict[str, Any]:
    kind = "internal" if status >= 500 else "usage"
    return {"error": {"kind": kind, "message": message, "exit_code": 4 if status >= 500 else 1}}


class _Handler(RequestHandler):
    def handle_error(
        self, request: BaseRequest, status: int = 500, exc: BaseException | None = None, message: str | None = None
    ) -> web.StreamResponse:
        if request.writer.output_size > 0:  # an answer was under way: nothing more can be said on it
            raise ConnectionError("the answer was already being sent")
        try:
            phrase = HTTPStatus(status).phrase
        except ValueError:
            phrase = "error"
        text = f"{phrase}: {message or exc or ''}".rstrip(": ")[:500]
        print(f"agent: bad request from {request.remote}: HTTP {status} {text}", file=sys.stderr, flush=True)
        resp = web.json_response(_body(status, text), status=status)
        resp.force_close()
        return resp

    def log_exception(self, *args: Any, **kw: Any) -> None:
        pass  # handle_error says it in one line


class _Server(web.Server):
    def __call__(self) -> RequestHandler:
        return _Handler(self, loop=self._loop, **self._kwargs)


class Runner(web.AppRunner):
    """``web.AppRunner`` whose connections answer unparseable requests as JSON."""

    async def _make_server(self) -> web.Server:
        server = await super()._make_server()
        server.__class__ = _Server  # the same server; only the handler it makes per connection differs
        return server
