"""The image helpers and the settings translation, without a coordinator."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import omis
from omis import bundle

from conftest import SCENES


def test_relmse_matches_its_definition() -> None:
    rng = np.random.default_rng(1)
    ref = rng.random((5, 7, 3), dtype=np.float32)
    img = ref + rng.normal(0, 0.1, ref.shape).astype(np.float32)
    d = img.astype(np.float64) - ref
    want = np.mean(d * d / (ref.astype(np.float64) ** 2 + 0.01))
    assert omis.relmse(img, ref) == pytest.approx(want, rel=1e-12)
    assert omis.relmse(ref, ref) == 0.0
    # Non-finite pixels are left out; a zero reference with eps 0 and no error is no error.
    img2 = img.copy()
    img2[0, 0, 1] = np.nan
    assert np.isfinite(omis.relmse(img2, ref))
    z = np.zeros((2, 2, 3), np.float32)
    assert omis.relmse(z, z, eps=0.0) == 0.0
    assert omis.relmse(img, ref, trim=0.1) < omis.relmse(img, ref)
    with pytest.raises(ValueError):
        omis.relmse(img, ref[:2])


def test_exr_round_trip(tmp_path: Path) -> None:
    img = np.arange(4 * 6 * 3, dtype=np.float32).reshape(4, 6, 3) / 7
    omis.write_exr(tmp_path / "a.exr", img)
    back = omis.read_exr(tmp_path / "a.exr")
    assert back.dtype == np.float32 and np.array_equal(back, img)
    assert list(omis.read_exr_layers(tmp_path / "a.exr")) == ["beauty"]
    with pytest.raises(KeyError):
        omis.read_exr(tmp_path / "a.exr", "depth0")


def test_tonemap_range() -> None:
    t = omis.tonemap(np.array([[[0.0, 0.5, 4.0]]], np.float32))
    assert t.min() >= 0 and t.max() <= 1 and t[0, 0, 2] == pytest.approx(1.0, abs=1e-6)


def test_flip_when_installed() -> None:
    pytest.importorskip("flip_evaluator")
    rng = np.random.default_rng(2)
    ref = rng.random((16, 16, 3), dtype=np.float32)
    mean, err = omis.flip(ref, ref)
    assert mean == pytest.approx(0.0, abs=1e-6) and err.shape == (16, 16)
    mean, err = omis.flip(ref * 2, ref)
    assert 0 < mean <= 1 and err.shape == (16, 16) and err.mean() == pytest.approx(mean, rel=1e-4)


def test_job_settings_python_names() -> None:
    s = omis.job_settings(
        {"time_budget": 2.5, "resolution": (64, 32), "spp": None, "defines": {"res": 8}}
    )
    assert s == {"time_budget_s": 2.5, "resolution": [64, 32], "defines": {"res": "8"}}


def test_named_files_follow_includes() -> None:
    got = bundle.named_files(SCENES / "mitsuba3" / "textures.xml")
    base = (SCENES / "mitsuba3").resolve()
    assert [p.relative_to(base).as_posix() for p in got] == ["parts/room.xml", "textures/grid.png"]
    # Nothing outside the scene's folder, nothing for a scene that names no file.
    assert bundle.named_files(SCENES / "veach-mis.json") == []


def test_pack_layout() -> None:
    scene = SCENES / "pbrt-v4" / "textures.pbrt"
    tar, main = bundle.pack(scene, bundle.named_files(scene))
    names = bundle.names_in(tar)
    assert main == "textures.pbrt" and names[0] == main
    assert all(not n.startswith(("/", "..")) for n in names)
