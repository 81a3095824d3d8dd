"""`Client` (one coordinator, embedded or remote) and `Job` (one render job)."""

from __future__ import annotations

import json
import os
import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator, Mapping, NamedTuple, Optional, Sequence, Union

import numpy as np
import numpy.typing as npt

from . import bundle as _bundle
from ._http import DEFAULT_TIMEOUT, Event, Transport
from .coordinator import EmbeddedCoordinator, find_binary
from .errors import CoordinatorError, JobCancelled, JobFailed, OmisError, ServiceError
from .images import BEAUTY, read_exr_layers, write_exr

#: A scene: a path to a file of any format omis reads, a dict in omis's JSON format (inline),
#: or the name of a scene of the coordinator's library (``"cornell-box"``,
#: ``"library:cornell-box"``).
Scene = Union[str, "os.PathLike[str]", Mapping[str, Any]]
#: A reference image: an EXR path, an H x W x 3 array, a finished `Job`, or a job request's
#: ``reference`` dict (``{"upload": id}``, ``{"job": id}``).
Reference = Union[str, "os.PathLike[str]", npt.ArrayLike, "Job", Mapping[str, str]]

#: Python spellings of job settings whose JSON names differ (the rest are the JSON names of
#: proto/openapi.yaml's JobSettings: spp, integrator, mis, max_depth, seed, ...).
SETTING_ALIASES = {"time_budget": "time_budget_s"}
#: Seconds `omis bundle` may take to load a scene and pack it.
BUNDLE_TIMEOUT = 600.0
#: Most uploads of one bundle while the coordinator names files it still misses.
MAX_BUNDLE_ROUNDS = 32


class SeriesPoint(NamedTuple):
    """One merged pass: seconds since the job started, samples per pixel so far, relMSE
    against the reference (None without one)."""

    seconds: float
    spp: int
    relmse: Optional[float]


@dataclass(frozen=True)
class Preview:
    """A job's 8-bit sRGB preview (PNG); shown inline by Jupyter."""

    data: bytes

    def _repr_png_(self) -> bytes:
        return self.data

    def save(self, path: Union[str, "os.PathLike[str]"]) -> None:
        """Writes the PNG."""
        Path(path).write_bytes(self.data)


def job_settings(settings: Mapping[str, Any]) -> dict[str, Any]:
    """The JSON job settings for keyword settings with Python names: aliases mapped
    (``time_budget`` -> ``time_budget_s``), tuples made lists; None values left out. Unknown
    names are sent as they are, and the coordinator refuses them with the field named."""
    out: dict[str, Any] = {}
    for k, v in settings.items():
        if v is None:
            continue
        k = SETTING_ALIASES.get(k, k)
        if isinstance(v, tuple):
            v = list(v)
        elif isinstance(v, Mapping):
            v = {str(a): str(b) for a, b in v.items()}
        out[k] = v
    return out


class Client:
    """A client of one omis coordinator.

    ``Client()`` starts an embedded coordinator (`omis serve` on a free loopback port, a
    temporary data folder, local workers) from `binary` (default: ``OMIS_BIN``, else `omis` on
    PATH), stopped on `close`, at the end of a ``with`` block, when the client is garbage
    collected, and at interpreter exit. ``Client(url, token)`` talks to a running coordinator.
    `workers`, `worker_threads` and `scenes` (the library folder) apply to the embedded one.
    """

    def __init__(
        self,
        url: Optional[str] = None,
        token: Optional[str] = None,
        binary: Union[str, "os.PathLike[str]", None] = None,
        *,
        workers: int = 1,
        worker_threads: Optional[int] = None,
        scenes: Union[str, "os.PathLike[str]", None] = None,
        timeout: float = DEFAULT_TIMEOUT,
    ) -> None:
        self.coordinator: Optional[EmbeddedCoordinator] = None
        #: The `omis` binary that packs scene bundles (`omis bundle`), when one is known.
        self.binary: Optional[str] = None
        if url is None:
            self.coordinator = EmbeddedCoordinator(
                binary,
                workers=workers,
                worker_threads=worker_threads,
                scenes=scenes,
                token=token,
            )
            url = self.coordinator.url
            self.binary = self.coordinator.binary
        else:
            try:
                self.binary = find_binary(binary)
            except CoordinatorError:
                self.binary = None
        if token is None and url is not None and self.coordinator is None:
            token = os.environ.get("OMIS_CLIENT_TOKEN") or os.environ.get("OMIS_TOKEN")
        self.url: str = url
        self._http = Transport(url, token, timeout)

    # ---- lifetime ----

    def close(self) -> None:
        """Stops the embedded coordinator, if any (its jobs and files go with it)."""
        if self.coordinator is not None:
            self.coordinator.stop()

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        kind = "embedded" if self.coordinator is not None else "remote"
        return f"<omis.Client {kind} {self.url}>"

    # ---- the service ----

    def health(self) -> dict[str, Any]:
        """``/healthz``: status and the server's version."""
        out: dict[str, Any] = self._http.json("GET", "/healthz", "health")
        return out

    def library(self) -> list[str]:
        """Names of the coordinator's library scenes."""
        out: list[str] = self._http.json("GET", "/v1/scenes", "listing the library")["library"]
        return out

    def jobs(
        self,
        state: Union[str, Sequence[str], None] = None,
        name: Optional[str] = None,
        since: Optional[float] = None,
    ) -> list["Job"]:
        """The jobs of the coordinator, oldest first (every page of GET /v1/jobs): those in
        `state` (a state or several: ``"done"``, ``("done", "failed")``), whose name contains
        `name` (case-insensitive), created at or after `since` (seconds since the epoch)."""
        query: dict[str, str] = {}
        if state is not None:
            query["state"] = state if isinstance(state, str) else ",".join(state)
        if name is not None:
            query["name"] = name
        if since is not None:
            query["since"] = repr(float(since))
        out: list[Job] = []
        after: Optional[str] = None
        while True:
            q = dict(query)
            if after is not None:
                q["after"] = after
            page = self._http.json("GET", "/v1/jobs", "listing the jobs", query=q)
            out.extend(Job(self, d["id"], d) for d in page["jobs"])
            nxt = page.get("next")
            if nxt is None or nxt == after:
                return out
            after = str(nxt)

    def job(self, job_id: str) -> "Job":
        """The job of that id (its status is fetched, so an unknown id raises)."""
        j = Job(self, job_id)
        j.status()
        return j

    def workers(self) -> list[dict[str, Any]]:
        """Every worker that ever registered (id, name, state, tasks, ...)."""
        out: list[dict[str, Any]] = self._http.json("GET", "/v1/workers", "listing workers")[
            "workers"
        ]
        return out

    # ---- uploads ----

    def upload_scene(
        self, scene: Union[str, "os.PathLike[str]"], defines: Optional[Mapping[str, str]] = None
    ) -> dict[str, Any]:
        """Uploads a scene file with the files it reads as a bundle; returns the coordinator's
        description of it (``id``, ``main``, ``files``, ``triangles``, ``warnings``, ...).

        With an `omis` binary at hand (`binary`), ``omis bundle`` packs it: the scene is loaded
        by omis's own importers and the bundle holds exactly the files they read, as `omis
        submit` uploads it. Without one, the first bundle holds the files the scene's text names
        (`omis.bundle.named_files`); while the coordinator answers that the scene reads a file
        the bundle lacks, that file is added and the bundle sent again."""
        path = Path(scene)
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no such scene file")
        if self.binary is not None:
            tar, main = self._pack_with_binary(path, defines)
            meta: dict[str, Any] = self._http.json(
                "POST",
                "/v1/scenes",
                "uploading the scene",
                query={"main": main},
                body=tar,
                content_type="application/x-tar",
            )
            return meta
        files = set(_bundle.named_files(path, defines))
        for _ in range(MAX_BUNDLE_ROUNDS):
            tar, main = _bundle.pack(path, files)
            try:
                meta = self._http.json(
                    "POST",
                    "/v1/scenes",
                    "uploading the scene",
                    query={"main": main},
                    body=tar,
                    content_type="application/x-tar",
                )
                return meta
            except ServiceError as e:
                more = set(_bundle.missing_files(path, e.message)) - files
                if e.status != 400 or not more:
                    raise
                files |= more
        raise ServiceError(400, f"{path}: the coordinator kept naming missing files", "body")

    def upload_frames(
        self,
        pattern: Union[str, "os.PathLike[str]"],
        frames: list[int],
        defines: Optional[Mapping[str, str]] = None,
    ) -> dict[str, Any]:
        """Uploads the scene files of `frames` of frame pattern `pattern` (``frame_####.xml``)
        with the files they read as one bundle whose main file is the pattern; returns the
        coordinator's description of it. ``omis bundle --frames`` packs it when an `omis`
        binary is at hand, else the files the scenes' text names are packed."""
        if self.binary is not None:
            first, last = frames[0], frames[-1]
            step = frames[1] - frames[0] if len(frames) > 1 else 1
            tar, main = self._pack_with_binary(
                Path(pattern), defines, ["--frames", f"{first}-{last}:{step}"]
            )
        else:
            tar, main = _bundle.pack_frames(pattern, frames, defines)
        meta: dict[str, Any] = self._http.json(
            "POST",
            "/v1/scenes",
            "uploading the sequence",
            query={"main": main},
            body=tar,
            content_type="application/x-tar",
        )
        return meta

    def _pack_with_binary(
        self, path: Path, defines: Optional[Mapping[str, str]], extra: Optional[list[str]] = None
    ) -> tuple[bytes, str]:
        """The bundle ``omis bundle`` packs for `path`, and its main file's name."""
        assert self.binary is not None
        with tempfile.TemporaryDirectory(prefix="omis-bundle-") as d:
            out = Path(d) / "bundle.tar"
            cmd = [self.binary, "bundle", str(path), "--out", str(out), *(extra or [])]
            for k, v in (defines or {}).items():
                cmd += ["--define", f"{k}={v}"]
            try:
                done = subprocess.run(
                    cmd, capture_output=True, timeout=BUNDLE_TIMEOUT, check=False
                )
            except subprocess.TimeoutExpired:
                raise OmisError(f"{path}: omis bundle took over {BUNDLE_TIMEOUT:.0f} s") from None
            if done.returncode != 0:
                line = done.stderr.decode("utf-8", "replace").strip().splitlines()
                raise OmisError(line[-1] if line else f"{path}: omis bundle failed")
            main = json.loads(done.stdout.decode("utf-8").strip().splitlines()[-1])["main"]
            return out.read_bytes(), str(main)

    def upload_reference(self, reference: Union[str, "os.PathLike[str]", npt.ArrayLike]) -> str:
        """Uploads a reference image (an EXR path or an H x W x 3 array); returns its id."""
        if isinstance(reference, (str, os.PathLike)):
            data = Path(reference).read_bytes()
        else:
            with tempfile.TemporaryDirectory(prefix="omis-ref-") as d:
                p = Path(d) / "reference.exr"
                write_exr(p, np.asarray(reference))
                data = p.read_bytes()
        info = self._http.json(
            "POST", "/v1/references", "uploading the reference", body=data,
            content_type="image/x-exr",
        )
        ref_id: str = info["id"]
        return ref_id

    def scene_source(self, scene: Scene, defines: Optional[Mapping[str, str]] = None) -> dict[str, Any]:
        """The ``scene`` of a job request: a dict goes inline, an existing file is uploaded as
        a bundle, a bare name (or ``library:name``) names a library scene."""
        if isinstance(scene, Mapping):
            return {"inline": dict(scene)}
        text = os.fspath(scene)
        p = Path(text)
        if p.is_file():
            return {"bundle": self.upload_scene(p, defines)["id"]}
        if text.startswith("library:"):
            return {"library": text[len("library:") :]}
        if len(p.parts) == 1 and "." not in text:
            return {"library": text}
        raise FileNotFoundError(
            f"{text}: no such scene file (a bare name is looked up in the coordinator's library)"
        )

    def reference_source(self, reference: Reference) -> dict[str, Any]:
        """The ``reference`` of a job request: a `Job` as ``{"job": id}``, a path or an array
        uploaded (``{"upload": id}``); a dict is taken as such a request already."""
        if isinstance(reference, Job):
            return {"job": reference.id}
        if isinstance(reference, Mapping):
            return dict(reference)
        return {"upload": self.upload_reference(reference)}

    # ---- jobs ----

    def submit(
        self,
        scene: Scene,
        *,
        reference: Optional[Reference] = None,
        name: Optional[str] = None,
        priority: Optional[int] = None,
        webhooks: Optional[list[dict[str, str]]] = None,
        frames: Optional[Union[str, tuple[int, ...]]] = None,
        **settings: Any,
    ) -> "Job":
        """Submits a render job; returns it at once (`Job.wait` follows it). Workers take the
        tasks of jobs of higher `priority` first (default 0), then of the oldest job.

        `settings` are the job settings of proto/openapi.yaml with Python names: ``spp=64,
        integrator="bdpt", mis="optimal", resolution=(320, 180), time_budget=10, seed=1,
        max_depth=5, depth_layers=True, strategies=True, defines={"res": "64"}, ...``. A bad
        one raises `ServiceError` whose ``field`` names it (``settings.spp``). `webhooks`:
        receivers of the job's end, ``[{"url": "http://...", "secret": "..."}]``.

        A sequence: `scene` a frame pattern (``frame_####.xml``) and ``frames=(1, 100)`` (or
        ``(1, 100, 2)``, ``"1-100"``); every frame file is uploaded in one bundle, each frame
        renders as a job of its own, and ``Job.download(path, frame=n)`` fetches one."""
        s = job_settings(settings)
        if frames is not None:
            if isinstance(scene, Mapping):
                raise ValueError("a sequence's scene is a frame pattern (frame_####.xml)")
            text, numbers = _bundle.frame_range(frames)
            bundle = self.upload_frames(scene, numbers, s.get("defines"))
            request: dict[str, Any] = {
                "scene": {"bundle": bundle["id"]},
                "settings": s,
                "frames": text,
            }
        else:
            request = {
                "scene": self.scene_source(scene, s.get("defines")),
                "settings": s,
            }
        if reference is not None:
            request["reference"] = self.reference_source(reference)
        if name is not None:
            request["name"] = name
        if priority is not None:
            request["priority"] = int(priority)
        if webhooks:
            request["webhooks"] = webhooks
        doc = self._http.json("POST", "/v1/jobs", "submitting the job", request)
        return Job(self, doc["id"], doc)

    def render(
        self,
        scene: Scene,
        *,
        layer: Optional[str] = None,
        progress: bool = False,
        timeout: Optional[float] = None,
        **settings: Any,
    ) -> npt.NDArray[np.float32]:
        """Submits, waits and returns the image (`layer`, default the beauty) as H x W x 3
        float32."""
        job = self.submit(scene, **settings)
        job.wait(progress=progress, timeout=timeout)
        return job.image(layer)


class Job:
    """One job of a coordinator: follow it, cancel it, fetch its images."""

    def __init__(self, client: Client, job_id: str, status: Optional[dict[str, Any]] = None):
        self.client = client
        self.id = job_id
        #: The last status document fetched.
        self.last_status: Optional[dict[str, Any]] = status
        self._exr: Optional[str] = None

    def __repr__(self) -> str:
        state = self.last_status["state"] if self.last_status else "?"
        return f"<omis.Job {self.id} {state}>"

    @property
    def _http(self) -> Transport:
        return self.client._http

    def status(self) -> dict[str, Any]:
        """The job's status document (state, spp_done, passes, eta_s, relmse, series, ...)."""
        doc: dict[str, Any] = self._http.json("GET", f"/v1/jobs/{self.id}", "job status")
        self.last_status = doc
        return doc

    @property
    def state(self) -> str:
        """``queued``, ``running``, ``paused``, ``done``, ``failed`` or ``cancelled`` (fetched
        now)."""
        state: str = self.status()["state"]
        return state

    def _control(self, action: str, what: str) -> dict[str, Any]:
        doc: dict[str, Any] = self._http.json("POST", f"/v1/jobs/{self.id}/{action}", what)
        self.last_status = doc
        return doc

    def cancel(self) -> dict[str, Any]:
        """Cancels the job; returns its status document. A job that has already ended raises
        `ServiceError` (409)."""
        return self._control("cancel", "cancelling")

    def pause(self) -> dict[str, Any]:
        """Pauses a queued or running job: no new tasks; those in hand finish and are kept.
        Returns its status document; any other state raises `ServiceError` (409)."""
        return self._control("pause", "pausing")

    def resume(self) -> dict[str, Any]:
        """Resumes a paused job; returns its status document (409 when not paused)."""
        return self._control("resume", "resuming")

    def requeue(self) -> dict[str, Any]:
        """Queues a failed job's failed tasks again (after a fix) and goes on with it; returns
        its status document (409 when it has not failed)."""
        return self._control("requeue", "requeuing")

    def retry(self) -> "Job":
        """Submits a failed or cancelled job again as a new job (same scene, settings,
        reference, name and priority); returns the new job, whose status names this one
        (``retry_of``)."""
        doc: dict[str, Any] = self._http.json("POST", f"/v1/jobs/{self.id}/retry", "retrying")
        return Job(self.client, doc["id"], doc)

    def set_priority(self, priority: int) -> dict[str, Any]:
        """Sets the priority of a job that has not ended (higher first); returns its status
        document."""
        doc: dict[str, Any] = self._http.json(
            "PATCH", f"/v1/jobs/{self.id}", "setting the priority", {"priority": int(priority)}
        )
        self.last_status = doc
        return doc

    def delete(self) -> None:
        """Deletes a job that has ended, with every file it stored (409 while it is active:
        cancel it first)."""
        self._http.read("DELETE", f"/v1/jobs/{self.id}", "deleting")
        self._exr = None

    def events(
        self, last_event_id: Optional[str] = None, timeout: Optional[float] = None
    ) -> Iterator[Event]:
        """The job's Server-Sent Events, from the first (or after `last_event_id`) until a
        terminal one (``done``, ``failed``, ``cancelled``). A broken stream is resumed with
        Last-Event-ID, so no event is seen twice or lost; `timeout` (seconds) bounds the whole
        iteration (`TimeoutError`)."""
        return self._http.events(f"/v1/jobs/{self.id}/events", last_event_id, timeout)

    def wait(self, progress: bool = True, timeout: Optional[float] = None) -> dict[str, Any]:
        """Follows the job until it ends, with a progress bar (tqdm: in a terminal, and as a
        widget in Jupyter) of tiles, with spp, passes and relMSE, and tqdm's ETA. Returns the
        final status document; raises `JobFailed` when the job failed, `TimeoutError` after
        `timeout` seconds."""
        st = self.last_status or self.status()
        bar = None
        passes = st.get("passes_total")
        if progress:
            from tqdm.auto import tqdm

            tiles = int(st.get("tiles_per_pass") or 0)
            total = passes * tiles if passes else None
            bar = tqdm(total=total, desc=f"job {self.id[:8]}", unit="tile", leave=True)
        try:
            for e in self.events(timeout=timeout):
                if bar is None:
                    continue
                if e.kind == "tile_done":
                    bar.update(1)
                elif e.kind == "pass_done":
                    done = int(e.data.get("pass", 0)) + 1
                    post = {"spp": e.data.get("spp"), "pass": f"{done}/{passes or '?'}"}
                    if e.data.get("relmse") is not None:
                        post["relMSE"] = f"{e.data['relmse']:.3e}"
                    bar.set_postfix(post)
                    if bar.total is None:
                        bar.refresh()
        finally:
            if bar is not None:
                bar.close()
        st = self.status()
        if st["state"] == "failed":
            raise JobFailed(self.id, st.get("error"), st)
        return st

    # ---- results ----

    def download(
        self,
        path: Union[str, "os.PathLike[str]"],
        file: str = "image.exr",
        frame: Optional[int] = None,
    ) -> Path:
        """Writes one of the job's files (``image.exr``, ``preview.png``, ``error.png``,
        ``convergence.svg``) to `path`; returns the path. A sequence's image and preview are
        per frame: `frame` says which."""
        kw: dict[str, Any] = {} if frame is None else {"query": {"frame": str(frame)}}
        data = self._http.read(
            "GET", f"/v1/jobs/{self.id}/{file}", f"downloading {file}", **kw
        )
        out = Path(path)
        out.write_bytes(data)
        return out

    def _image_file(self) -> str:
        """The job's EXR in a temporary file; kept once the job has ended (its EXR is final)."""
        if self._exr is not None and os.path.exists(self._exr):
            return self._exr
        st = self.status()
        if st["state"] == "cancelled" and st.get("passes_done", 0) == 0:
            raise JobCancelled(f"job {self.id} was cancelled before any pass was merged")
        fd, tmp = tempfile.mkstemp(prefix=f"omis-{self.id[:8]}-", suffix=".exr")
        os.close(fd)
        try:
            self.download(tmp)
        except BaseException:
            os.unlink(tmp)
            raise
        if st["state"] in ("done", "cancelled", "failed"):
            self._exr = tmp
            import weakref

            weakref.finalize(self, _unlink, tmp)
        return tmp

    def image_layers(self) -> dict[str, npt.NDArray[np.float32]]:
        """Every layer of the job's EXR by name (``beauty``, ``s1_t2``, ``depth0``, ...)."""
        path = self._image_file()
        try:
            return read_exr_layers(path)
        finally:
            if path != self._exr:
                _unlink(path)

    def image(self, layer: Optional[str] = None) -> npt.NDArray[np.float32]:
        """The job's image as an H x W x 3 float32 array: the beauty, or the layer of that name
        (strategies ``s<S>_t<T>`` with ``strategies=True``, depths ``depth<d>`` with
        ``depth_layers=True``). While the job runs, its last rewritten EXR."""
        layers = self.image_layers()
        name = layer or BEAUTY
        if name not in layers:
            raise KeyError(f"job {self.id} has no layer '{name}' (it has: {', '.join(layers)})")
        return layers[name]

    def layers(self) -> list[str]:
        """Names of the layers of the job's EXR (``beauty`` first)."""
        names = list(self.image_layers())
        return sorted(names, key=lambda n: (n != BEAUTY, n))

    def relmse_series(self) -> list[SeriesPoint]:
        """(seconds, spp, relMSE) per merged pass; relMSE is None without a reference."""
        return [
            SeriesPoint(float(p["seconds"]), int(p["spp"]), p.get("relmse"))
            for p in self.status().get("series", [])
        ]

    def preview(self) -> Preview:
        """The 8-bit sRGB preview of the last merged pass (shown inline in Jupyter)."""
        return Preview(self._http.read("GET", f"/v1/jobs/{self.id}/preview.png", "preview"))


def _unlink(path: str) -> None:
    try:
        os.unlink(path)
    except OSError:
        pass

