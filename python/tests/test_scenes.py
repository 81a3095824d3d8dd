"""Every kind of scene through a real coordinator: a JSON dict, a JSON file, Mitsuba 3 XML and
pbrt-v4 with includes and textures, a shared scene, a library name. Bundles packed here hold
the same files, byte for byte, as the bundles `omis submit` packs."""

from __future__ import annotations

import io
import json
import subprocess
import tarfile
from pathlib import Path

import numpy as np
import pytest

import omis
from omis import bundle

from conftest import SCENES, shared_scene

TINY = {"resolution": (16, 16), "spp": 2, "pass_size": 1}


def worker_bundle(client: omis.Client, bundle_id: str) -> dict[str, bytes]:
    """The files of a stored bundle, as a worker downloads them (the embedded coordinator
    checks no worker token on loopback)."""
    data = client._http.read("GET", f"/v1/worker/scenes/{bundle_id}", "bundle")
    with tarfile.open(fileobj=io.BytesIO(data)) as tar:
        out = {}
        for m in tar.getmembers():
            if m.isfile():
                f = tar.extractfile(m)
                assert f is not None
                out[m.name] = f.read()
        return out


def submitted_bundle(client: omis.Client, omis_bin: str, scene: Path) -> dict[str, bytes]:
    """The bundle `omis submit` uploads for `scene`."""
    out = subprocess.run(
        [omis_bin, "submit", str(scene), "--server", client.url, "--spp", "1",
         "--resolution", "8x8"],
        capture_output=True, text=True, timeout=120, check=True,
    )
    job = client.job(out.stdout.strip().splitlines()[-1])
    return worker_bundle(client, job.status()["scene"]["id"])


def check_image(img: np.ndarray, shape: tuple[int, int]) -> None:
    assert img.dtype == np.float32
    assert img.shape == (shape[1], shape[0], 3)
    assert np.isfinite(img).all()
    assert img.mean() > 0


def test_json_dict_inline(client: omis.Client) -> None:
    scene = json.loads((SCENES / "cornell-box.json").read_text())
    img = client.render(scene, **TINY)
    check_image(img, TINY["resolution"])


def test_json_file(client: omis.Client) -> None:
    img = client.render(SCENES / "veach-mis.json", integrator="bdpt", **TINY)
    check_image(img, TINY["resolution"])


def test_library_name(client: omis.Client) -> None:
    assert "cornell-box" in client.library()
    job = client.submit("cornell-box", **TINY)
    job.wait(progress=False, timeout=120)
    assert job.status()["scene"]["main"].startswith("cornell-box")
    check_image(job.image(), TINY["resolution"])
    job2 = client.submit("library:cornell-box", **TINY)
    assert job2.wait(progress=False, timeout=120)["state"] == "done"


FILE_SCENES = sorted(
    p.relative_to(SCENES).as_posix()
    for p in [*SCENES.glob("mitsuba3/*.xml"), *SCENES.glob("pbrt-v4/*.pbrt"), *SCENES.glob("*.json")]
)


@pytest.mark.parametrize("scene", FILE_SCENES)
def test_bundles_equal_omis_submits(client: omis.Client, omis_bin: str, scene: str) -> None:
    path = SCENES / scene
    ours = worker_bundle(client, client.upload_scene(path)["id"])
    theirs = submitted_bundle(client, omis_bin, path)
    assert ours == theirs, (sorted(ours), sorted(theirs))


@pytest.mark.parametrize(
    "scene,expected",
    [
        ("mitsuba3/textures.xml", {"textures.xml", "parts/room.xml", "textures/grid.png"}),
        ("mitsuba3/environment-map.xml", {"environment-map.xml", "textures/sky.exr"}),
        ("pbrt-v4/textures.pbrt", None),
        ("pbrt-v4/instances.pbrt", None),
    ],
)
def test_file_formats_render(client: omis.Client, scene: str, expected: set[str] | None) -> None:
    path = SCENES / scene
    meta = client.upload_scene(path)
    assert len(meta["files"]) > 1, "the scene reads other files"
    if expected is not None:
        assert set(meta["files"]) == expected
    job = client.submit(path, **TINY)
    job.wait(progress=False, timeout=120)
    check_image(job.image(), TINY["resolution"])


def test_shared_veach_mis(client: omis.Client, omis_bin: str) -> None:
    path = shared_scene("veach-mis", "mitsuba", "scene.xml")
    # The folder also holds a reference render the scene does not read: it stays out.
    assert bundle.named_files(path) == []
    assert set(worker_bundle(client, client.upload_scene(path)["id"])) == {"scene.xml"}
    img = client.render(path, integrator="bdpt", mis="optimal", resolution=(32, 18), spp=2)
    check_image(img, (32, 18))


def test_files_a_text_scan_misses_are_packed(
    client: omis.Client, tmp_path: Path
) -> None:
    # A file named in a way the text scan cannot see (built from a define's default in two
    # parts) is still packed: the coordinator names it as missing and the client adds it.
    src = (SCENES / "mitsuba3" / "textures.xml").read_text()
    (tmp_path / "parts").mkdir()
    (tmp_path / "textures").mkdir()
    (tmp_path / "parts" / "room.xml").write_bytes((SCENES / "mitsuba3/parts/room.xml").read_bytes())
    (tmp_path / "textures" / "grid.png").write_bytes(
        (SCENES / "mitsuba3/textures/grid.png").read_bytes()
    )
    src = src.replace('<default name="spp" value="64"/>',
                      '<default name="spp" value="64"/>\n    <default name="dir" value="parts"/>')
    src = src.replace('<include filename="parts/room.xml"/>', '<include filename="$dir/room.xml"/>')
    scene = tmp_path / "scene.xml"
    scene.write_text(src)
    assert tmp_path / "parts" / "room.xml" not in bundle.named_files(scene)
    expected = {"scene.xml", "parts/room.xml", "textures/grid.png"}
    # With the binary at hand, `omis bundle` packs what the importer read.
    assert client.binary is not None
    assert set(client.upload_scene(scene)["files"]) == expected
    # Without one (a remote coordinator, no omis installed), the scan and the coordinator's
    # answers find the same files.
    scanner = omis.Client(client.url, client._http.token)
    scanner.binary = None
    assert set(scanner.upload_scene(scene)["files"]) == expected


def test_missing_scene_file(client: omis.Client) -> None:
    with pytest.raises(FileNotFoundError):
        client.submit("no/such/scene.xml")
