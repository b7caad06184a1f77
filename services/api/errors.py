"""Every error the API answers has the body ``{"code", "message"}``, with ``details`` for an invalid
request: the service's own (:class:`ApiError`, raised by the routes with a stable code), the framework's
HTTP errors (an unmatched route, a method not allowed, an upload over the limit) and request validation
errors.  A refused POST counts in the metrics under its code."""

from __future__ import annotations

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from services.api import schemas
from services.api.limits import TOO_LARGE

#: The error responses each route documents.
ERRORS = {code: {"model": schemas.Error} for code in (400, 401, 404, 409, 413, 415, 422, 503)}
#: Codes for the framework's own HTTP errors.
HTTP_CODES = {400: "bad_request", 404: "not_found", 405: "method_not_allowed"}


class ApiError(Exception):
    """An error a route answers: HTTP ``status``, a stable ``code`` and a ``message`` that says what is
    wrong and what is expected."""

    def __init__(self, status: int, code: str, message: str):
        self.status, self.code, self.message = status, code, message


def install(app: FastAPI) -> None:
    """Register the handlers that give every error the service's shape."""

    @app.exception_handler(ApiError)
    async def _api_error(request: Request, exc: ApiError):
        if request.method == "POST":
            request.app.state.metrics.rejected(exc.code)
        return JSONResponse({"code": exc.code, "message": exc.message}, status_code=exc.status)

    # Starlette's class, not FastAPI's subclass: an unmatched route raises Starlette's.
    @app.exception_handler(StarletteHTTPException)
    async def _http_error(request: Request, exc: StarletteHTTPException):
        if request.scope.get(TOO_LARGE):
            limit = request.app.state.settings.max_upload_bytes
            return await _api_error(request, ApiError(413, "upload_too_large",
                                                      f"the upload is larger than this server's limit of {limit} bytes."))
        message = str(exc.detail)
        if exc.status_code == 404 and request.scope.get("route") is None:
            message = f"no such route: {request.method} {request.url.path} (see /docs for the API)."
        return JSONResponse({"code": HTTP_CODES.get(exc.status_code, "http_error"), "message": message},
                            status_code=exc.status_code, headers=getattr(exc, "headers", None))

    @app.exception_handler(RequestValidationError)
    async def _invalid(request: Request, exc: RequestValidationError):
        errors = [{"loc": list(map(str, e.get("loc", ()))), "msg": e.get("msg", "")} for e in exc.errors()]
        message = "; ".join(f"{'.'.join(e['loc'][1:] or e['loc'])}: {e['msg']}" for e in errors) or "invalid request"
        request.app.state.metrics.rejected("invalid_request")
        return JSONResponse({"code": "invalid_request", "message": message, "details": errors}, status_code=422)
