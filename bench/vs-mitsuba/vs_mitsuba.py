"""omis's path tracer against Mitsuba 3's, noise per sample (run by bench/vs-mitsuba/run).

Each renderer renders every scene twice at the same spp, with seeds 1 and 2. Noise per render =
half the mean over pixels of (seed 1 - seed 2)^2 / (ref^2 + 0.01), the channels averaged: the
variance part of relMSE alone, so a bias of either renderer does not count. ref is the Tungsten
reference beside the staircase (box-downsampled to the resolution), and for the boxes a Mitsuba 3
render at --ref-spp. "trimmed" leaves the 0.1 % of pixels with the largest value out (fireflies).

Scenes:
- staircase: ../shared/scenes/staircase/mitsuba/scene.xml (Mitsuba 0.5). omis reads it as it is;
  Mitsuba 3's strict parser needs three edits (drop `strictNormals` and `extEta`, `trilinear` ->
  `bilinear`), and gets an hdrfilm with a box filter and the independent sampler. Max depth 64
  (Mitsuba's 65: it counts the emitter vertex).
- cbox-mixed: bench/vs-mitsuba/cbox-mixed.xml (diffuse walls, rough gold, glass, rough plastic),
  max depth 7 (Mitsuba's 8).
- cbox-diffuse: scenes/mitsuba3/cbox-diffuse.xml, max depth 7 (Mitsuba's 8).

CPU-s: Mitsuba's is the process time of `mi.render` (scene loading excluded); omis's the CPU time
of the `omis render --in-process` process (loading included). Timings of a loaded machine mean
nothing: compare noise, or run on an idle machine.
"""

import argparse
import json
import os
import re
import resource
import subprocess
import sys
import tempfile
import time

import mitsuba as mi
import numpy as np

mi.set_log_level(mi.LogLevel.Warn)

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(os.path.dirname(HERE))
STAIRCASE = os.path.join(ROOT, "..", "shared", "scenes", "staircase", "mitsuba")


def noise(a, b, ref, eps=0.01, trim=0.001):
    """(noise per render, the same without the `trim` fraction of the largest pixels)."""
    per_pixel = (np.mean((a - b) ** 2 / (ref**2 + eps), axis=-1) / 2).ravel()
    kept = np.sort(per_pixel)[: max(1, int(round(len(per_pixel) * (1 - trim))))]
    return float(per_pixel.mean()), float(kept.mean())


def read_exr(path):
    return np.array(mi.Bitmap(path), dtype=np.float64)[..., :3]


def staircase_for_mitsuba3(tmp, width, height, max_depth):
    """The staircase file with the edits Mitsuba 3's parser needs, written into `tmp`."""
    s = open(os.path.join(STAIRCASE, "scene.xml")).read()
    s = re.sub(r'\s*<boolean name="strictNormals"[^>]*/>', "", s)
    s = re.sub(r'\s*<float name="extEta"[^>]*/>', "", s)
    s = s.replace('"trilinear"', '"bilinear"')
    s = re.sub(r'(<integer name="maxDepth" value=")\d+(")', rf"\g<1>{max_depth + 1}\g<2>", s)
    s = re.sub(r"<sampler .*?</sampler>",
               '<sampler type="independent"><integer name="sampleCount" value="16"/></sampler>',
               s, flags=re.S)
    s = re.sub(r"<film .*?</film>",
               f'<film type="hdrfilm"><integer name="width" value="{width}"/>'
               f'<integer name="height" value="{height}"/><rfilter type="box"/></film>',
               s, flags=re.S)
    path = os.path.join(tmp, "staircase-mitsuba3.xml")
    open(path, "w").write(s)
    return path


def box_downsample(img, width, height):
    h, w, _ = img.shape
    if w % width or h % height or w // width != h // height:
        raise SystemExit(f"the reference ({w}x{h}) does not box-downsample to {width}x{height}")
    f = w // width
    return img.reshape(height, f, width, f, 3).mean(axis=(1, 3))


def mitsuba_renders(variant, path, spp, seeds, defines, search=None):
    mi.set_variant(variant)
    if search:
        mi.file_resolver().prepend(search)
    scene = mi.load_file(path, **defines)
    out = []
    for seed in seeds:
        t = time.process_time()
        img = np.array(mi.render(scene, spp=spp, seed=seed), dtype=np.float64)[..., :3]
        out.append((img, time.process_time() - t))
    return out


def omis_renders(omis, path, spp, seeds, max_depth, res, extra, tmp):
    out = []
    for seed in seeds:
        exr = os.path.join(tmp, f"omis-{seed}.exr")
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        r = subprocess.run(
            [omis, "render", path, "--in-process", "--spp", str(spp), "--seed", str(seed),
             "--max-depth", str(max_depth), "--resolution", res, "--out", exr, "--json"]
            + extra, capture_output=True, text=True)
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        if r.returncode != 0:
            raise SystemExit(f"omis render {path}: {r.stderr.strip()}")
        summary = json.loads(r.stdout.strip().splitlines()[-1])
        cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
        rays = summary.get("rays", 0) / (summary["width"] * summary["height"] * spp)
        out.append((read_exr(exr), cpu, rays))
    return out


def table(name, rows, ref):
    print(f"\n### {name} (reference mean {ref.mean():.4f})\n")
    print("| renderer | image mean | noise per render | trimmed (0.1 %) | noise vs Mitsuba 3 "
          "| rays per sample | CPU-s | efficiency 1/(noise x CPU-s), vs Mitsuba 3 |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    base = None
    for label, renders in rows:
        (a, ca, *ra), (b, cb, *rb) = renders
        n, t = noise(a, b, ref)
        cpu = (ca + cb) / 2
        eff = 1.0 / (n * cpu)
        if base is None:
            base = (n, eff)
        rays = f"{(ra[0] + rb[0]) / 2:.2f}" if ra else ""
        print(f"| {label} | {(a.mean() + b.mean()) / 2:.4f} | {n:.4f} | {t:.4f} "
              f"| {n / base[0]:.2f}x | {rays} | {cpu:.1f} | {eff / base[1]:.2f}x |")
    sys.stdout.flush()


def main():
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--omis", required=True, help="the omis binary")
    p.add_argument("--omis-before", help="another omis binary to compare (e.g. of main)")
    p.add_argument("--scenes", default="staircase,cbox-mixed,cbox-diffuse")
    p.add_argument("--variants", default="scalar_rgb",
                   help="Mitsuba 3 variants, comma-separated (llvm_ad_rgb needs libLLVM)")
    p.add_argument("--staircase-res", default="180x320",
                   help="a box-downsampling of 720x1280 (the issue's: 360x640)")
    p.add_argument("--staircase-spp", type=int, default=16)
    p.add_argument("--box-res", type=int, default=128)
    p.add_argument("--box-spp", type=int, default=64)
    p.add_argument("--ref-spp", type=int, default=1024, help="the boxes' Mitsuba 3 reference")
    a = p.parse_args()

    seeds = (1, 2)
    omis_bins = [("omis pt", a.omis)]
    if a.omis_before:
        omis_bins.append(("omis pt (before)", a.omis_before))
    with tempfile.TemporaryDirectory() as tmp:
        for name in a.scenes.split(","):
            if name == "staircase":
                w, h = (int(x) for x in a.staircase_res.split("x"))
                max_depth, spp, res = 64, a.staircase_spp, a.staircase_res
                omis_path = os.path.join(STAIRCASE, "scene.xml")
                mi_path = staircase_for_mitsuba3(tmp, w, h, max_depth)
                defines, search = {}, STAIRCASE
                ref = box_downsample(read_exr(os.path.join(STAIRCASE, "TungstenRender.exr")), w, h)
            else:
                path = (os.path.join(HERE, "cbox-mixed.xml") if name == "cbox-mixed"
                        else os.path.join(ROOT, "scenes", "mitsuba3", f"{name}.xml"))
                max_depth, spp, res = 7, a.box_spp, f"{a.box_res}x{a.box_res}"
                omis_path = mi_path = path
                search = None
                defines = {"res": str(a.box_res), "max_depth": str(max_depth + 1)}
                ref = mitsuba_renders("scalar_rgb", mi_path, a.ref_spp, (7,), defines)[0][0]
            rows = []
            for v in a.variants.split(","):
                try:
                    rows.append((f"Mitsuba 3 `{v}`", mitsuba_renders(v, mi_path, spp, seeds, defines,
                                                                   search)))
                except Exception as e:  # a variant this machine cannot run (no libLLVM)
                    print(f"Mitsuba 3 {v}: skipped ({e})", file=sys.stderr)
            for label, binary in omis_bins:
                for sampler in ("sobol", "independent"):
                    rows.append((f"{label}, {sampler}",
                                 omis_renders(binary, omis_path, spp, seeds, max_depth, res,
                                              ["--sampler", sampler], tmp)))
            table(f"{name}, {res}, {spp} spp, max depth {max_depth} (Mitsuba's {max_depth + 1})",
                  rows, ref)


if __name__ == "__main__":
    main()
