"""Fixtures: a real `omis serve` (embedded, with one local worker) shared by the tests, and
the repository's scenes. The binary is OMIS_BIN, else target/ci/omis, else `omis` on PATH."""

from __future__ import annotations

import os
import shutil
from pathlib import Path
from typing import Iterator

import pytest

import omis

REPO = Path(__file__).resolve().parents[2]
SCENES = REPO / "scenes"
SHARED = REPO.parent / "shared" / "scenes"


def binary() -> str:
    """The omis binary the tests run."""
    if os.environ.get("OMIS_BIN"):
        return os.environ["OMIS_BIN"]
    target = Path(os.environ.get("CARGO_TARGET_DIR", REPO / "target"))
    built = target / "ci" / "omis"
    if built.is_file():
        return str(built)
    found = shutil.which("omis")
    if found is None:
        pytest.fail("no omis binary: set OMIS_BIN or build it (cargo build --profile ci)")
    return found


def pids_of_group(pgid: int) -> list[int]:
    """Live processes of a process group (the embedded coordinator and its workers)."""
    out = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
        except OSError:
            continue
        # Fields after the command name (which may hold spaces): state ppid pgrp ...
        fields = stat[stat.rindex(")") + 2 :].split()
        if int(fields[2]) == pgid and fields[0] != "Z":
            out.append(int(entry.name))
    return out


def shared_scene(*parts: str) -> Path:
    """A scene of ../shared/scenes; skipped when absent, except in CI (CI=true), where it
    fails."""
    p = SHARED.joinpath(*parts)
    if not p.is_file():
        if os.environ.get("CI"):
            pytest.fail(f"{p} is missing (CI needs ../shared/scenes)")
        pytest.skip(f"{p} is missing")
    return p


@pytest.fixture(scope="session")
def omis_bin() -> str:
    return binary()


@pytest.fixture(scope="session")
def client(omis_bin: str) -> Iterator[omis.Client]:
    c = omis.Client(binary=omis_bin, workers=1, worker_threads=2, scenes=SCENES)
    assert c.coordinator is not None
    pgid = c.coordinator.pid
    try:
        yield c
    finally:
        c.close()
        assert pids_of_group(pgid) == [], "the embedded coordinator outlived close()"
