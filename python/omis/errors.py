"""The exceptions of the omis client."""

from __future__ import annotations

from typing import Any, Optional


class OmisError(Exception):
    """Base class of every error this package raises."""


class ServiceError(OmisError):
    """The coordinator refused a request: its JSON error body (``error``, ``field``) and the
    HTTP status.

    ``field`` names what the error is about: a JSON path of the request (``settings.spp``,
    ``scene.library``), a query parameter, a header (``Authorization``) or a path parameter
    (``id``), as proto/openapi.yaml describes.
    """

    def __init__(
        self,
        status: int,
        message: str,
        field: Optional[str] = None,
        body: Optional[Any] = None,
        what: str = "",
    ) -> None:
        self.status = status
        self.message = message
        self.field = field
        self.body = body
        self.what = what
        where = f" ({field})" if field else ""
        prefix = f"{what}: " if what else ""
        super().__init__(f"{prefix}HTTP {status}: {message}{where}")


class ConnectionFailed(OmisError):
    """The coordinator could not be reached (refused, reset, or no answer in time)."""


class CoordinatorError(OmisError):
    """The embedded coordinator (``omis serve``) could not be started or stopped."""


class JobFailed(OmisError):
    """A job ended in state ``failed`` (``status`` is its last status document)."""

    def __init__(self, job_id: str, error: Optional[str], status: dict[str, Any]) -> None:
        self.job_id = job_id
        self.error = error
        self.status = status
        super().__init__(f"job {job_id} failed: {error or 'no error given'}")


class JobCancelled(OmisError):
    """A job's result was asked for, but the job was cancelled before it had any pass."""
