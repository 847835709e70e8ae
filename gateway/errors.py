"""The errors of the gateway's episode logic; :func:`gateway.app.create_app` turns each into its HTTP answer
with one exception handler (``status_code``, ``detail``, ``Retry-After`` when given)."""

from __future__ import annotations

from typing import Any


class GatewayError(Exception):
    """Base of the errors the routes answer with ``status_code``."""

    status_code = 400

    def __init__(self, message: str, field: str | None = None, retry_after_s: float | None = None) -> None:
        super().__init__(message)
        self.message = message
        self.field = field
        self.retry_after_s = retry_after_s

    def detail(self) -> Any:
        if self.field:
            return [{"loc": ["body", self.field], "msg": self.message, "type": "value_error"}]
        return self.message


class NotFoundError(GatewayError):
    status_code = 404


class BusyError(GatewayError):
    status_code = 409


class ConflictError(GatewayError):
    status_code = 409


class InvalidError(GatewayError):
    status_code = 422


class TooManyError(GatewayError):
    """A queue limit (per robot, per token) is reached: 429 with ``Retry-After``."""

    status_code = 429
