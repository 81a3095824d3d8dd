"""omis from Python: submit scenes to the omis render service (an embedded coordinator or a
running one), follow jobs, get images as numpy arrays.

>>> import omis
>>> img = omis.render("scenes/veach-mis.json", spp=16, integrator="bdpt", mis="optimal")
>>> with omis.Client() as c:
...     job = c.submit("scenes/mitsuba3/textures.xml", spp=64)
...     job.wait()
...     img = job.image()
"""

from ._http import Event
from .api import close_default_client, default_client, render
from .bundle import named_files, pack
from .client import Client, Job, Preview, SeriesPoint, job_settings
from .compare import CompareResult, compare
from .coordinator import EmbeddedCoordinator, find_binary
from .errors import (
    ConnectionFailed,
    CoordinatorError,
    JobCancelled,
    JobFailed,
    OmisError,
    ServiceError,
)
from .images import flip, read_exr, read_exr_layers, relmse, tonemap, write_exr

__version__ = "0.1.0"

__all__ = [
    "Client",
    "CompareResult",
    "ConnectionFailed",
    "CoordinatorError",
    "EmbeddedCoordinator",
    "Event",
    "Job",
    "JobCancelled",
    "JobFailed",
    "OmisError",
    "Preview",
    "SeriesPoint",
    "ServiceError",
    "close_default_client",
    "compare",
    "default_client",
    "find_binary",
    "flip",
    "job_settings",
    "named_files",
    "pack",
    "read_exr",
    "read_exr_layers",
    "relmse",
    "render",
    "tonemap",
    "write_exr",
]
