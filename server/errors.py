"""Domain errors raised by service functions; the app turns them into HTTP responses."""

from __future__ import annotations


class ServiceError(Exception):
    status_code = 400

    def __init__(self, detail: str, retry_after: int | None = None) -> None:
        super().__init__(detail)
        self.detail = detail
        self.retry_after = retry_after


class NotFound(ServiceError):
    status_code = 404


class Conflict(ServiceError):
    status_code = 409


class Unauthorized(ServiceError):
    status_code = 401


class Forbidden(ServiceError):
    status_code = 403


class TooManyRequests(ServiceError):
    status_code = 429


class Unprocessable(ServiceError):
    """Well-formed input that names something unknown (e.g. a condition the rendered clip set lacks)."""

    status_code = 422


class PayloadTooLarge(ServiceError):
    """A request body over its limit (an upload over ``ANIMSTUDY_UPLOAD_MAX_BYTES``)."""

    status_code = 413


class MediaError(ValueError):
    """The clip set to render is missing or inconsistent, or the cluster that renders it cannot run the job (the
    message says which).  Not an HTTP error: a command reports it as one line, a job stores it as its error."""
