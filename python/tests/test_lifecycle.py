"""The embedded coordinator's lifetime (stopped with its workers on close, on an exception, when
a test fails, at interpreter exit) and the client token."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

import omis

from conftest import SCENES, pids_of_group


def wait_gone(pgid: int, timeout: float = 20.0) -> list[int]:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        left = pids_of_group(pgid)
        if not left:
            return []
        time.sleep(0.1)
    return pids_of_group(pgid)


def workers_up(c: omis.Client, timeout: float = 20.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and not c.workers():
        time.sleep(0.1)


def test_context_exit_on_exception_stops_coordinator_and_workers(omis_bin: str) -> None:
    with pytest.raises(RuntimeError):
        with omis.Client(binary=omis_bin, workers=2, worker_threads=1) as c:
            assert c.coordinator is not None
            pgid = c.coordinator.pid
            data = c.coordinator.data
            workers_up(c)
            assert len(pids_of_group(pgid)) >= 2, "coordinator and its workers"
            raise RuntimeError("the caller fails")
    assert wait_gone(pgid) == []
    assert not os.path.exists(data)


def run_python(code: str, tmp_path: Path, *args: str) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(
        [str(Path(omis.__file__).resolve().parents[1]), str(Path(__file__).parent)]
    )
    script = tmp_path / "script.py"
    script.write_text(textwrap.dedent(code))
    return subprocess.run(
        [sys.executable, *args, str(script)], capture_output=True, text=True, timeout=120,
        env=env, cwd=tmp_path,
    )


def test_stopped_when_a_test_fails(omis_bin: str, tmp_path: Path) -> None:
    pid_file = tmp_path / "pid"
    code = f"""
        import pytest, omis

        @pytest.fixture
        def client():
            c = omis.Client(binary={omis_bin!r})
            yield c
            c.close()

        def test_fails_with_a_fixture(client):
            open({str(pid_file)!r} + "1", "w").write(str(client.coordinator.pid))
            assert False, "this test fails on purpose"

        def test_fails_without_closing():
            c = omis.Client(binary={omis_bin!r})
            open({str(pid_file)!r} + "2", "w").write(str(c.coordinator.pid))
            assert False, "this test fails on purpose"
    """
    r = run_python(code, tmp_path, "-m", "pytest", "-q", "-p", "no:cacheprovider")
    assert r.returncode == 1, r.stdout + r.stderr
    assert r.stdout.count("this test fails on purpose") >= 2
    for n in "12":
        pgid = int(Path(str(pid_file) + n).read_text())
        assert wait_gone(pgid) == []


def test_stopped_at_interpreter_exit_without_close(omis_bin: str, tmp_path: Path) -> None:
    code = f"""
        import omis
        c = omis.Client(binary={omis_bin!r})
        print(c.coordinator.pid, flush=True)
        print(c.coordinator.data, flush=True)
        raise SystemExit(3)
    """
    r = run_python(code, tmp_path)
    assert r.returncode == 3, r.stderr
    pid, data = r.stdout.split()
    assert wait_gone(int(pid)) == []
    assert not os.path.exists(data)


def test_token_protected_coordinator(omis_bin: str) -> None:
    with omis.Client(token="right-token", binary=omis_bin, workers=0) as c:
        assert c.jobs() == []
        wrong = omis.Client(c.url, token="wrong-token")
        with pytest.raises(omis.ServiceError) as e:
            wrong.jobs()
        assert e.value.status == 401 and e.value.field == "Authorization"
        with pytest.raises(omis.ServiceError) as e:
            omis.Client(c.url).submit(SCENES / "veach-mis.json")
        assert e.value.status == 401
        # A remote client does not own the coordinator: closing it stops nothing.
        wrong.close()
        assert c.coordinator is not None and c.coordinator.running


def test_bad_binary() -> None:
    with pytest.raises(omis.CoordinatorError):
        omis.Client(binary="/nonexistent/omis")
