"""The client's one exception: the server's error code, message and field, from HTTP or gRPC."""

from __future__ import annotations

import re
from typing import Any

# The server's gRPC status messages start with its error's text (crates/core/src/error.rs); these prefixes give
# back the JSON API's stable code, and the backquoted name gives the field.
_GRPC_MESSAGE_CODES = [
    ("malformed request:", "malformed_request"),
    ("invalid field `", "invalid_field"),
    ("insufficient data in `", "insufficient_data"),
    ("request body exceeds", "payload_too_large"),
    ("server overloaded", "overloaded"),
    ("not found:", "not_found"),
    ("forbidden:", "forbidden"),
    ("request timed out", "timeout"),
    ("not ready:", "unavailable"),
    ("model bundle:", "bundle_error"),
    ("runtime:", "runtime_error"),
    ("io:", "io_error"),
]
_FIELD = re.compile(r"^(?:invalid field|insufficient data in) `([^`]+)`")


class PosefuseError(Exception):
    """An error answered by the server (or a transport failure, with code ``transport_error``).

    Attributes:
        code: the server's stable error code (``invalid_field``, ``malformed_request``,
            ``overloaded``, ``timeout``, ``unavailable``, ...).
        message: the server's message, naming the field when there is one.
        field: the offending field as a JSON path (``persons[0].box_3d.height``), or None.
        http_status: the HTTP status, for errors from the HTTP API.
        grpc_status: the gRPC status code name (``INVALID_ARGUMENT``), for errors from gRPC.
    """

    def __init__(
        self,
        code: str,
        message: str,
        field: str | None = None,
        *,
        http_status: int | None = None,
        grpc_status: str | None = None,
    ) -> None:
        super().__init__(f"{code}: {message}" if field is None else f"{code} ({field}): {message}")
        self.code = code
        self.message = message
        self.field = field
        self.http_status = http_status
        self.grpc_status = grpc_status

    @property
    def retryable(self) -> bool:
        """True for errors worth retrying later (queue full, warming up or draining, deadline)."""
        return self.code in ("overloaded", "unavailable", "timeout", "transport_error")

    @classmethod
    def from_http(cls, status: int, body: bytes) -> PosefuseError:
        """From an HTTP error response with the `{"error": {"code", "message", "field"}}` body."""
        import json

        try:
            detail: Any = json.loads(body)["error"]
            return cls(detail["code"], detail["message"], detail.get("field"), http_status=status)
        except (ValueError, KeyError, TypeError):
            text = body.decode("utf-8", "replace")[:500]
            return cls(f"http_{status}", text or f"HTTP {status}", http_status=status)

    @classmethod
    def from_grpc(cls, status_name: str, message: str) -> PosefuseError:
        """From a gRPC status: the code is read back from the message's prefix."""
        code, field = grpc_message_code(message, status_name)
        return cls(code, message, field, grpc_status=status_name)


def grpc_message_code(message: str, status_name: str) -> tuple[str, str | None]:
    """(error code, field) of a server error message (gRPC status or stream error item)."""
    code = next((c for prefix, c in _GRPC_MESSAGE_CODES if message.startswith(prefix)), status_name.lower())
    m = _FIELD.match(message)
    return code, m.group(1) if m else None
