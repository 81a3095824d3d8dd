"""The one-call entry points: `render` on a shared embedded coordinator."""

from __future__ import annotations

import os
import threading
from typing import Any, Optional, Union

import numpy as np
import numpy.typing as npt

from .client import Client, Scene

_default: Optional[Client] = None
_lock = threading.Lock()


def default_client(binary: Union[str, "os.PathLike[str]", None] = None) -> Client:
    """The client `render` and `compare` use without one: an embedded coordinator started on
    first use (from `binary`, ``OMIS_BIN`` or PATH) and stopped at interpreter exit; or, when
    ``OMIS_SERVER`` is set, the coordinator at that URL (with ``OMIS_CLIENT_TOKEN``)."""
    global _default
    with _lock:
        if _default is None or (
            _default.coordinator is not None and not _default.coordinator.running
        ):
            server = os.environ.get("OMIS_SERVER")
            token = os.environ.get("OMIS_CLIENT_TOKEN") or os.environ.get("OMIS_TOKEN")
            _default = Client(server, token, binary)
        return _default


def close_default_client() -> None:
    """Stops the shared embedded coordinator now (it is stopped at exit anyway)."""
    global _default
    with _lock:
        if _default is not None:
            _default.close()
            _default = None


def render(
    scene: Scene,
    *,
    client: Optional[Client] = None,
    layer: Optional[str] = None,
    progress: bool = False,
    timeout: Optional[float] = None,
    **settings: Any,
) -> npt.NDArray[np.float32]:
    """Renders `scene` (a path, a JSON dict or a library name) locally and returns the image
    as an H x W x 3 float32 array, like Mitsuba's ``mi.render``. `settings` are job settings
    with Python names (``spp=64, integrator="bdpt", mis="optimal", resolution=(320, 180)``)."""
    c = client or default_client()
    return c.render(scene, layer=layer, progress=progress, timeout=timeout, **settings)
