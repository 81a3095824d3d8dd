"""An embedded coordinator: `omis serve` on a free loopback port, with a temporary data folder
and local worker processes, stopped with its workers when closed, when its owner is garbage
collected, and at interpreter exit."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import tempfile
import threading
import weakref
from typing import IO, Optional, Union

from .errors import CoordinatorError

#: Seconds to wait for `omis serve` to print its address.
START_TIMEOUT = 30.0
#: Seconds `omis serve` has to drain its workers after SIGTERM before it is killed.
STOP_TIMEOUT = 15.0


def find_binary(binary: Union[str, os.PathLike[str], None] = None) -> str:
    """The `omis` binary: `binary` when given, else the ``OMIS_BIN`` environment variable,
    else `omis` on PATH."""
    if binary is not None:
        candidate = str(binary)
    elif os.environ.get("OMIS_BIN"):
        candidate = os.environ["OMIS_BIN"]
    else:
        found = shutil.which("omis")
        if found is None:
            raise CoordinatorError(
                "no omis binary: pass binary=..., set OMIS_BIN, or put omis on PATH"
            )
        candidate = found
    if not (os.path.isfile(candidate) and os.access(candidate, os.X_OK)):
        raise CoordinatorError(f"{candidate}: not an executable omis binary")
    return candidate


def _stop(proc: subprocess.Popen[bytes], data: Optional[str]) -> None:
    """SIGTERM to the coordinator's process group (the coordinator and its local workers),
    SIGKILL to it when it outlives STOP_TIMEOUT, then the data folder is removed."""
    try:
        if proc.poll() is None:
            _signal_group(proc.pid, signal.SIGTERM)
            try:
                proc.wait(timeout=STOP_TIMEOUT)
            except subprocess.TimeoutExpired:
                _signal_group(proc.pid, signal.SIGKILL)
                proc.wait(timeout=STOP_TIMEOUT)
        # Workers left behind by a coordinator that died first go with their group.
        _signal_group(proc.pid, signal.SIGKILL)
    finally:
        for stream in (proc.stdout, proc.stderr):
            if stream is not None:
                stream.close()
        if data is not None:
            shutil.rmtree(data, ignore_errors=True)


def _drain(stream: Optional[IO[bytes]]) -> None:
    if stream is None:
        return
    try:
        while stream.read(1 << 16):
            pass
    except (OSError, ValueError):
        pass


def _signal_group(pgid: int, sig: int) -> None:
    try:
        os.killpg(pgid, sig)
    except (ProcessLookupError, PermissionError):
        pass


class EmbeddedCoordinator:
    """`omis serve --bind 127.0.0.1:0` as a child process in a process group of its own.

    `workers` local worker processes of `worker_threads` threads each (default: one worker
    with a thread per core). `scenes` is the scene library folder (default: ``scenes`` of the
    current folder, as `omis serve`'s). `token`, when given, is required of clients. `data`
    is the data folder (default: a temporary folder, removed on stop).
    """

    def __init__(
        self,
        binary: Union[str, os.PathLike[str], None] = None,
        *,
        workers: int = 1,
        worker_threads: Optional[int] = None,
        scenes: Union[str, os.PathLike[str], None] = None,
        token: Optional[str] = None,
        data: Union[str, os.PathLike[str], None] = None,
        extra_args: tuple[str, ...] = (),
        start_timeout: float = START_TIMEOUT,
    ) -> None:
        self.binary = find_binary(binary)
        own_data = data is None
        self.data = tempfile.mkdtemp(prefix="omis-py-") if own_data else str(data)
        threads = worker_threads or os.cpu_count() or 1
        args = [
            self.binary,
            "serve",
            "--bind",
            "127.0.0.1:0",
            "--data",
            self.data,
            "--workers",
            str(workers),
            "--worker-threads",
            str(threads),
        ]
        if scenes is not None:
            args += ["--scenes", str(scenes)]
        args += list(extra_args)
        env = dict(os.environ)
        env.setdefault("OMIS_LOG", "warn")
        env.pop("OMIS_TOKEN", None)
        env.pop("OMIS_CLIENT_TOKEN", None)
        env.pop("OMIS_WORKER_TOKEN", None)
        if token is not None:
            # Through the environment: a command line is visible to every local user.
            env["OMIS_CLIENT_TOKEN"] = token
        self._log = tempfile.TemporaryFile()
        try:
            self.process: subprocess.Popen[bytes] = subprocess.Popen(
                args,
                stdin=subprocess.DEVNULL,
                stdout=subprocess.PIPE,
                stderr=self._log,
                env=env,
                start_new_session=True,
            )
        except OSError as e:
            self._log.close()
            if own_data:
                shutil.rmtree(self.data, ignore_errors=True)
            raise CoordinatorError(f"cannot start {self.binary} serve: {e}") from None
        self.pid = self.process.pid
        self._finalizer = weakref.finalize(
            self, _stop, self.process, self.data if own_data else None
        )
        line = self._first_line(start_timeout)
        if not line.startswith("listening on "):
            log = self.log()
            self.stop()
            raise CoordinatorError(
                f"omis serve did not start: {line.strip() or 'no address printed'}; "
                f"its log: {log.strip()[-2000:]}"
            )
        #: The coordinator's base URL (``http://127.0.0.1:PORT``).
        self.url = line[len("listening on ") :].strip()
        # Whatever it (or a worker) prints later is read, so that a full pipe never blocks it.
        threading.Thread(target=_drain, args=(self.process.stdout,), daemon=True).start()

    def _first_line(self, timeout: float) -> str:
        result: list[bytes] = []
        out = self.process.stdout
        assert out is not None

        def read() -> None:
            result.append(out.readline())

        reader = threading.Thread(target=read, daemon=True)
        reader.start()
        reader.join(timeout)
        if reader.is_alive():
            self.stop()
            raise CoordinatorError(f"omis serve printed no address within {timeout} s")
        return result[0].decode("utf-8", "replace") if result else ""

    def log(self) -> str:
        """What the coordinator wrote to stderr so far."""
        try:
            self._log.seek(0)
            return self._log.read().decode("utf-8", "replace")
        except (OSError, ValueError):
            return ""

    @property
    def running(self) -> bool:
        """Whether the coordinator process is alive."""
        return self.process.poll() is None

    def stop(self) -> None:
        """Stops the coordinator and its workers, removes the temporary data folder (safe to
        call more than once)."""
        self._finalizer()
        self._log.close()

    def __enter__(self) -> "EmbeddedCoordinator":
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

