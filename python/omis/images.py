"""Images as numpy arrays: omis's EXRs read with OpenEXR's own Python package, relMSE as omis
computes it, and FLIP through the `flip-evaluator` package when it is installed."""

from __future__ import annotations

import os
from typing import Any, Optional, Union

import numpy as np
import numpy.typing as npt

#: The name of the beauty layer (channels ``R, G, B`` without a prefix).
BEAUTY = "beauty"

PathLike = Union[str, "os.PathLike[str]"]


def read_exr_layers(path: PathLike) -> dict[str, npt.NDArray[np.float32]]:
    """Every RGB layer of an EXR: the beauty (``R, G, B``, or a gray ``Y``) as ``"beauty"``,
    and each ``<name>.R/G/B`` group as ``name`` (strategy layers ``s1_t2``, depth layers
    ``depth0``, ...); each an H x W x 3 float32 array."""
    import OpenEXR

    with OpenEXR.File(os.fspath(path), separate_channels=True) as f:
        channels = f.parts[0].channels
        groups: dict[str, dict[str, npt.NDArray[np.float32]]] = {}
        for name, ch in channels.items():
            layer, _, comp = name.rpartition(".")
            groups.setdefault(layer or BEAUTY, {})[comp] = np.asarray(ch.pixels)
    out: dict[str, npt.NDArray[np.float32]] = {}
    for layer, comps in groups.items():
        if all(c in comps for c in "RGB"):
            rgb = [comps[c] for c in "RGB"]
        elif "Y" in comps:
            rgb = [comps["Y"]] * 3
        else:
            continue
        out[layer] = np.ascontiguousarray(np.stack(rgb, axis=-1), dtype=np.float32)
    return out


def read_exr(path: PathLike, layer: Optional[str] = None) -> npt.NDArray[np.float32]:
    """One layer of an EXR as an H x W x 3 float32 array: the beauty by default, else the
    layer of that name (see `read_exr_layers`)."""
    layers = read_exr_layers(path)
    name = layer or BEAUTY
    if name not in layers:
        raise KeyError(f"{os.fspath(path)} has no layer '{name}' (it has: {', '.join(layers)})")
    return layers[name]


def write_exr(path: PathLike, image: npt.ArrayLike) -> None:
    """Writes an H x W x 3 image as a float32 RGB EXR (ZIP-compressed)."""
    import OpenEXR

    img = _rgb(image, "image")
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    channels = {c: np.ascontiguousarray(img[..., i]) for i, c in enumerate("RGB")}
    with OpenEXR.File(header, channels) as f:
        f.write(os.fspath(path))


def _rgb(image: npt.ArrayLike, what: str) -> npt.NDArray[np.float32]:
    a = np.asarray(image, dtype=np.float32)
    if a.ndim == 2:
        a = np.repeat(a[..., None], 3, axis=-1)
    if a.ndim != 3 or a.shape[-1] not in (3, 4):
        raise ValueError(f"{what} must be H x W x 3, not {a.shape}")
    return a[..., :3]


def relmse(
    image: npt.ArrayLike, reference: npt.ArrayLike, eps: float = 0.01, trim: float = 0.0
) -> float:
    """relMSE = mean over pixels and channels of (I - R)^2 / (R^2 + eps) (the MRSE of Cailleau
    et al., "Optimal Multiple Importance Sampling for Bidirectional Path Tracing"; what
    `omis diff` and the service report), computed in float64; pixels where either image is not
    finite are left out. `trim` leaves out that fraction of pixels with the largest error
    (omis reports 0.001 as relMSE trimmed)."""
    a = _rgb(image, "image").astype(np.float64)
    r = _rgb(reference, "reference").astype(np.float64)
    if a.shape != r.shape:
        raise ValueError(f"size mismatch: image is {a.shape[:2]}, reference is {r.shape[:2]}")
    ok = np.isfinite(a).all(-1) & np.isfinite(r).all(-1)
    a, r = a[ok], r[ok]
    d = a - r
    with np.errstate(divide="ignore", invalid="ignore"):
        per = np.where(d != 0.0, d * d / (r * r + eps), 0.0).sum(-1)
    n = per.size
    if n == 0:
        return 0.0
    drop = min(int(np.ceil(n * trim)), n - 1) if trim > 0 else 0
    if drop > 0:
        per = np.partition(per, n - drop)[: n - drop]
    return float(per.sum() / (3 * per.size))


def flip(
    image: npt.ArrayLike, reference: npt.ArrayLike, **parameters: Any
) -> tuple[float, npt.NDArray[np.float32]]:
    """HDR-FLIP of `image` against `reference` (Andersson et al., "FLIP: A Difference Evaluator
    for Alternating Images", HPG 2020; the HDR variant of 2021): the mean FLIP value and the
    per-pixel error map (H x W). `parameters` go to `flip_evaluator.evaluate` (``ppd``,
    ``tonemapper``, ...). Needs the `flip-evaluator` package (``pip install omis[flip]``)."""
    try:
        import flip_evaluator
    except ImportError:
        raise ImportError(
            "omis.flip needs the flip-evaluator package: pip install flip-evaluator"
        ) from None
    a = np.ascontiguousarray(_rgb(image, "image"))
    r = np.ascontiguousarray(_rgb(reference, "reference"))
    # Linear inputs, and the error itself rather than its magma colouring.
    error_map, mean, _ = flip_evaluator.evaluate(
        r, a, "HDR", inputsRGB=False, applyMagma=False, parameters=parameters
    )
    err = np.asarray(error_map, dtype=np.float32)
    return float(mean), err.reshape(err.shape[0], err.shape[1])


def tonemap(image: npt.ArrayLike, exposure: float = 0.0) -> npt.NDArray[np.float32]:
    """An sRGB-encoded copy of a linear image in [0, 1] (for display), after scaling by
    2^exposure."""
    a = np.clip(_rgb(image, "image") * np.float32(2.0**exposure), 0.0, 1.0)
    out: npt.NDArray[np.float32] = np.where(
        a <= 0.0031308, 12.92 * a, 1.055 * np.power(a, 1 / 2.4) - 0.055
    ).astype(np.float32)
    return out
