"""Errors in a frame that its sender can act on (not an EXR, unsupported, too large, missing or
ambiguous channels), each with the HTTP status and code the service answers with.

Here, below the service, because the frame reading that raises them (exr_header, exr_channels,
exr_codec) is shared with the scene readers; service/errors.py derives the service's other
errors from ServiceError and converts them all to HTTP at its boundary.
"""

from __future__ import annotations


class ServiceError(Exception):
    """An error the service answers with `status` and `code` (and `detail`, `headers`)."""

    status = 500
    code = "internal_error"

    def __init__(self, detail: str, *, headers: dict[str, str] | None = None) -> None:
        super().__init__(detail)
        self.detail = detail
        self.headers = headers or {}


class BadExr(ServiceError):
    """Not an EXR, truncated, corrupt."""

    status, code = 400, "bad_exr"


class ExrHeaderTooLarge(ServiceError):
    """The EXR header's attributes exceed QUIETFRAME_MAX_HEADER_BYTES."""

    status, code = 413, "exr_header_too_large"


class ResolutionTooLarge(ServiceError):
    status, code = 413, "resolution_too_large"


class UnsupportedExr(ServiceError):
    """Deep data, subsampled channels."""

    status, code = 422, "unsupported_exr"


class MissingChannels(ServiceError):
    status, code = 422, "missing_channels"


class AmbiguousChannels(ServiceError):
    status, code = 422, "ambiguous_channels"


class SizeMismatch(ServiceError):
    status, code = 422, "size_mismatch"
