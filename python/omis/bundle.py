"""Scene bundles: a tar archive of a scene file and the files it reads (meshes, textures,
includes), with paths relative to the scene's folder, as `omis submit` packs them.

Which files a scene reads is known for certain only to the importers of the omis binary. This
module makes the first guess from the scene's text: every quoted string or attribute value of
the scene file, and of the text files it names (.xml, .pbrt, .json includes), that names a file
inside the scene's folder. The coordinator then loads the uploaded bundle and names any file it
still misses (``'parts/x.obj' not found``); `Client` adds those and uploads again
(`missing_files`). Files outside the scene's folder are refused by the importers, so they are
never packed.
"""

from __future__ import annotations

import io
import os
import re
import tarfile
from pathlib import Path
from typing import Iterable, Mapping, Optional, Union

#: Extensions of files scanned for further file names (includes of pbrt and Mitsuba files).
TEXT_EXTENSIONS = (".xml", ".pbrt", ".json")
#: Most files followed while scanning (a scene with more has them added by the coordinator's
#: answers instead).
MAX_SCANNED = 1000
#: Largest text file scanned for names, in bytes (larger ones are mesh data, not scene text).
MAX_SCAN_BYTES = 64 << 20

_QUOTED = re.compile(r"\"([^\"\r\n]{1,4096})\"|'([^'\r\n]{1,4096})'")
_MISSING = re.compile(r"'([^'\r\n]+)' (?:not found|is not a file)")


def scene_folder(scene: Path) -> Path:
    """The folder every path of `scene` is relative to (the importers' `scene_folder`)."""
    return scene.resolve().parent


def _inside(base: Path, rel: str) -> Optional[Path]:
    """`rel` as a file inside `base`, or None (absolute, leaving the folder, or not a file)."""
    rel = rel.strip()
    if not rel or "\x00" in rel or os.path.isabs(rel) or rel.startswith(("\\", "/")):
        return None
    p = base / rel
    try:
        real = p.resolve()
    except (OSError, RuntimeError):
        return None
    if not real.is_relative_to(base) or not real.is_file():
        return None
    return Path(os.path.normpath(p))


def named_files(scene: Path, defines: Optional[Mapping[str, str]] = None) -> list[Path]:
    """The files inside the scene's folder that its text (and its included text files') names,
    sorted, without the scene file itself."""
    base = scene_folder(scene)
    main = Path(os.path.normpath(base / scene.name))
    found: set[Path] = set()
    todo = [main]
    scanned: set[Path] = set()
    extra = list((defines or {}).values())
    for value in extra:
        f = _inside(base, value)
        if f is not None:
            found.add(f)
            todo.append(f)
    while todo and len(scanned) < MAX_SCANNED:
        f = todo.pop()
        if f in scanned or f.suffix.lower() not in TEXT_EXTENSIONS:
            continue
        scanned.add(f)
        try:
            if f.stat().st_size > MAX_SCAN_BYTES:
                continue
            text = f.read_text("utf-8", errors="replace")
        except OSError:
            continue
        for m in _QUOTED.finditer(text):
            value = m.group(1) if m.group(1) is not None else m.group(2)
            g = _inside(base, value)
            if g is not None and g != main and g not in found:
                found.add(g)
                todo.append(g)
    found.discard(main)
    return sorted(found)


def missing_files(scene: Path, message: str) -> list[Path]:
    """The files inside the scene's folder that an error message of the coordinator names as
    not found in the bundle."""
    base = scene_folder(scene)
    out = []
    for m in _MISSING.finditer(message):
        f = _inside(base, m.group(1))
        if f is not None:
            out.append(f)
    return out


def pack(scene: Union[str, os.PathLike[str]], files: Iterable[Path]) -> tuple[bytes, str]:
    """A tar archive of `scene` (at its top level) and `files` (paths inside its folder, kept
    relative to it); returns the archive and the scene file's name in it."""
    scene = Path(scene)
    base = scene_folder(scene)
    main = scene.name
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w", format=tarfile.GNU_FORMAT) as tar:
        _add(tar, scene, main)
        for f in sorted(set(files)):
            rel = Path(os.path.normpath(f)).relative_to(Path(os.path.normpath(base)))
            name = rel.as_posix()
            if name == main:
                continue
            _add(tar, f, name)
    return buf.getvalue(), main


def frame_file(pattern: str, frame: int) -> str:
    """The file of `frame` in a frame pattern (``frame_####.xml``): its file name's run of
    ``#`` replaced by the frame number, zero-padded to the run's length."""
    head, sep, name = pattern.rpartition("/")
    m = re.fullmatch(r"([^#]*)(#+)([^#]*)", name)
    if m is None:
        raise ValueError(f"{pattern!r} is not a frame pattern (one run of '#' in its file name)")
    width = len(m.group(2))
    return f"{head}{sep}{m.group(1)}{frame:0{width}d}{m.group(3)}"


def frame_range(frames: Union[str, tuple[int, ...]]) -> tuple[str, list[int]]:
    """A sequence's frames, ``"1-100"``, ``"1-100:2"``, ``(1, 100)`` or ``(1, 100, 2)``, as the
    request's text and the frame numbers."""
    if isinstance(frames, str):
        m = re.fullmatch(r"\s*(\d+)\s*(?:-\s*(\d+)\s*(?::\s*(\d+)\s*)?)?", frames)
        if m is None:
            raise ValueError(f"{frames!r} is not a frame range (FIRST-LAST or FIRST-LAST:STEP)")
        first = int(m.group(1))
        last = int(m.group(2)) if m.group(2) else first
        step = int(m.group(3)) if m.group(3) else 1
    else:
        parts = tuple(int(x) for x in frames)
        if len(parts) not in (2, 3):
            raise ValueError(f"{frames!r}: (first, last) or (first, last, step)")
        first, last = parts[0], parts[1]
        step = parts[2] if len(parts) == 3 else 1
    if step < 1 or first > last:
        raise ValueError(f"{frames!r}: an empty frame range")
    return f"{first}-{last}:{step}", list(range(first, last + 1, step))


def pack_frames(
    pattern: Union[str, os.PathLike[str]],
    frames: list[int],
    defines: Optional[Mapping[str, str]] = None,
) -> tuple[bytes, str]:
    """A tar archive of the scene files of `frames` of `pattern` and the files their text
    names (shared ones once); returns the archive and the pattern's file name (its main)."""
    text = os.fspath(pattern)
    scenes = [Path(frame_file(text, f)) for f in frames]
    for s in scenes:
        if not s.is_file():
            raise FileNotFoundError(f"{s}: no such frame file")
    files: set[Path] = set(scenes[1:])
    for s in scenes:
        files |= set(named_files(s, defines))
    tar, _ = pack(scenes[0], files)
    return tar, Path(text).name


def _add(tar: tarfile.TarFile, path: Path, name: str) -> None:
    # A link is packed as the file it points at (the coordinator refuses links in bundles).
    with open(path, "rb") as fh:
        st = os.fstat(fh.fileno())
        info = tarfile.TarInfo(name)
        info.size = st.st_size
        info.mtime = int(st.st_mtime)
        info.mode = 0o644
        tar.addfile(info, fh)


def names_in(archive: bytes) -> list[str]:
    """The file names of a bundle, in archive order."""
    with tarfile.open(fileobj=io.BytesIO(archive), mode="r") as tar:
        return [m.name for m in tar.getmembers() if m.isfile()]
