"""Jobs: events with Last-Event-ID resume, the array against the EXR's pixels, layers,
references and relMSE, cancel, errors with the field named, compare, the listings."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import OpenEXR
import pytest

import omis

from conftest import SCENES

VEACH = SCENES / "veach-mis.json"
SMALL = {"resolution": (24, 16), "pass_size": 1, "max_pass_size": 1}


def exr_pixels(path: Path) -> dict[str, np.ndarray]:
    """Channels of an EXR through OpenEXR's scan-line reader (the legacy InputFile API, not
    the File API `omis.read_exr` uses)."""
    f = OpenEXR.InputFile(str(path))
    try:
        header = f.header()
        dw = header["dataWindow"]
        w, h = dw.max.x - dw.min.x + 1, dw.max.y - dw.min.y + 1
        out = {}
        for name in header["channels"]:
            out[name] = np.frombuffer(f.channel(name), dtype=np.float32).reshape(h, w)
        return out
    finally:
        f.close()


@pytest.fixture(scope="module")
def done_job(client: omis.Client) -> omis.Job:
    job = client.submit(VEACH, integrator="bdpt", spp=4, strategies=True, depth_layers=True,
                        **SMALL)
    st = job.wait(progress=True, timeout=120)
    assert st["state"] == "done"
    return job


def test_events_and_resume(client: omis.Client, done_job: omis.Job) -> None:
    events = list(done_job.events(timeout=60))
    kinds = [e.kind for e in events]
    assert kinds[0] == "queued" and kinds[-1] == "done"
    assert kinds.count("pass_done") == 4 and "tile_done" in kinds
    ids = [int(e.id) for e in events if e.id is not None]
    assert ids == sorted(ids) and len(ids) == len(events)
    assert all(e.data["job"] == done_job.id for e in events)
    # Resuming after the third event gives exactly the rest.
    rest = list(done_job.events(last_event_id=events[2].id, timeout=60))
    assert rest == events[3:]


def test_image_equals_the_exr_bit_for_bit(done_job: omis.Job, tmp_path: Path) -> None:
    exr = done_job.download(tmp_path / "image.exr")
    raw = exr_pixels(exr)
    img = done_job.image()
    assert img.dtype == np.float32 and img.shape == (16, 24, 3)
    expected = np.stack([raw["R"], raw["G"], raw["B"]], axis=-1)
    assert np.array_equal(img.view(np.uint32), expected.view(np.uint32))
    assert np.array_equal(omis.read_exr(exr).view(np.uint32), expected.view(np.uint32))
    # Every layer, by name.
    layers = done_job.layers()
    assert layers[0] == "beauty"
    assert "depth0" in layers and "s1_t1" in layers
    for name in ("depth1", "s1_t1"):
        lay = done_job.image(name)
        want = np.stack([raw[f"{name}.{c}"] for c in "RGB"], axis=-1)
        assert np.array_equal(lay.view(np.uint32), want.view(np.uint32))
    with pytest.raises(KeyError):
        done_job.image("no-such-layer")


def test_preview_and_files(done_job: omis.Job, tmp_path: Path) -> None:
    p = done_job.preview()
    assert p.data.startswith(b"\x89PNG") and p._repr_png_() == p.data
    svg = done_job.download(tmp_path / "c.svg", "convergence.svg")
    assert svg.read_bytes().lstrip().startswith(b"<")


def test_reference_relmse_series(client: omis.Client, done_job: omis.Job) -> None:
    ref = done_job.image()
    for reference in (done_job, ref):
        job = client.submit(VEACH, integrator="bdpt", mis="optimal", spp=2, seed=7,
                            reference=reference, **SMALL)
        st = job.wait(progress=False, timeout=120)
        series = job.relmse_series()
        assert [p.spp for p in series] == [1, 2]
        assert all(p.relmse is not None and p.relmse > 0 for p in series)
        assert series[-1].seconds >= series[0].seconds
        assert st["relmse"] == pytest.approx(omis.relmse(job.image(), ref), rel=1e-6)


def test_cancel(client: omis.Client) -> None:
    job = client.submit(VEACH, integrator="bdpt", spp=65536, resolution=(64, 64))
    st = job.cancel()
    assert st["state"] == "cancelled"
    kinds = [e.kind for e in job.events(timeout=60)]
    assert kinds[-1] == "cancelled"
    assert job.wait(progress=False, timeout=60)["state"] == "cancelled"
    with pytest.raises(omis.ServiceError) as e:
        job.cancel()
    assert e.value.status == 409 and e.value.field == "id"


@pytest.mark.parametrize(
    "settings,field,status",
    [
        ({"spp": 0}, "settings.spp", 422),
        ({"mis": "optimal"}, "settings.mis", 422),
        ({"integrator": "whitted"}, "settings.integrator", 422),
        ({"no_such_setting": 1}, "settings.no_such_setting", 422),
        ({"time_budget": -1}, "settings.time_budget_s", 422),
        ({"resolution": (0, 10)}, "settings.resolution", 422),
    ],
)
def test_bad_setting_names_the_field(
    client: omis.Client, settings: dict, field: str, status: int
) -> None:
    with pytest.raises(omis.ServiceError) as e:
        client.submit(VEACH, **settings)
    assert e.value.status == status
    assert e.value.field is not None and e.value.field.startswith(field), e.value
    assert e.value.message and isinstance(e.value.body, dict)
    assert field in str(e.value)


def test_unknown_job_and_library_scene(client: omis.Client) -> None:
    with pytest.raises(omis.ServiceError) as e:
        client.job("00000000-0000-0000-0000-000000000000")
    assert e.value.status == 404 and e.value.field == "id"
    with pytest.raises(omis.ServiceError) as e:
        client.submit("no-such-library-scene")
    assert e.value.field == "scene.library"


def test_listings(client: omis.Client, done_job: omis.Job) -> None:
    assert done_job.id in [j.id for j in client.jobs()]
    workers = client.workers()
    assert workers and all("state" in w for w in workers)
    assert client.health()["status"] == "ok"


def test_compare(client: omis.Client, done_job: omis.Job) -> None:
    result = omis.compare(VEACH, done_job, mis=["balance", "optimal"], spp=[1, 2],
                          equal_time=0.5, seeds=1, client=client, **SMALL)
    assert len(result.records) == 6
    assert {r["mis"] for r in result.records} == {"balance", "optimal"}
    assert all(r["relmse"] is not None and r["relmse"] > 0 for r in result.records)
    df = result.df
    assert df is not None and len(df) == 6
    import matplotlib

    matplotlib.use("Agg")
    figs = result.plots()
    assert set(figs) == {"relmse_vs_spp", "relmse_vs_time"}


def test_render_with_default_client(omis_bin: str, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("OMIS_BIN", omis_bin)
    monkeypatch.delenv("OMIS_SERVER", raising=False)
    try:
        img = omis.render(VEACH, spp=1, resolution=(8, 8))
        assert img.shape == (8, 8, 3)
        c = omis.default_client()
        assert c.coordinator is not None and c.coordinator.running
    finally:
        omis.close_default_client()
