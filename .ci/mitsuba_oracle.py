"""Mitsuba 3 as the oracle of its own files (run by .ci/mitsuba-oracle).

For every scene of scenes/mitsuba3/ (or those named): Mitsuba 3 renders a reference at
--ref-spp and --seeds renders at --spp; omis renders --seeds renders at --spp from the same file.
relMSE = mean over pixels and channels of (I - R)^2 / (R^2 + eps), against Mitsuba's reference
(also without the 0.1 % of pixels with the largest error, per image).
A scene passes when omis's mean is within --mean-tol of the reference's, per channel, and omis's
mean relMSE is within --ratio of Mitsuba's own. Prints a table and exits 1 on any failure.
"""

import argparse
import glob
import json
import os
import subprocess
import sys
import tempfile
import time

import mitsuba as mi
import numpy as np

mi.set_variant("scalar_rgb")
mi.set_log_level(mi.LogLevel.Warn)


def read_exr(path):
    return np.array(mi.Bitmap(path), dtype=np.float64)[..., :3]


def relmse(img, ref, eps, trim=0.0):
    """Mean over pixels of the channel-mean relative squared error, without the `trim` fraction
    of worst pixels."""
    per_pixel = np.mean((img - ref) ** 2 / (ref**2 + eps), axis=-1).ravel()
    if trim > 0:
        per_pixel = np.sort(per_pixel)[: max(1, int(round(len(per_pixel) * (1 - trim))))]
    return float(np.mean(per_pixel))


def mitsuba_render(scene, spp, seed):
    t = time.process_time()
    img = np.array(mi.render(scene, spp=spp, seed=seed), dtype=np.float64)[..., :3]
    return img, time.process_time() - t


def omis_render(omis, path, spp, seed, out):
    t = time.time()
    r = subprocess.run(
        [omis, "render", path, "--in-process", "--spp", str(spp), "--seed", str(seed),
         "--out", out, "--json"],
        capture_output=True, text=True)
    if r.returncode != 0:
        raise SystemExit(f"omis render {path}: {r.stderr.strip()}")
    summary = json.loads(r.stdout.strip().splitlines()[-1])
    return read_exr(out), summary.get("seconds", time.time() - t), r.stderr


def main():
    a = argparse.ArgumentParser()
    a.add_argument("--omis", required=True)
    a.add_argument("--spp", type=int, default=32)
    a.add_argument("--ref-spp", type=int, default=2048)
    a.add_argument("--seeds", type=int, default=4)
    a.add_argument("--eps", type=float, default=0.01)
    a.add_argument("--mean-tol", type=float, default=0.01)
    a.add_argument("--ratio", type=float, default=1.5)
    a.add_argument("scenes", nargs="*")
    args = a.parse_args()
    scenes = args.scenes or sorted(glob.glob("scenes/mitsuba3/*.xml"))
    work = tempfile.mkdtemp(prefix="omis-oracle-")
    rows, failed = [], []
    for path in scenes:
        name = os.path.basename(path)
        scene = mi.load_file(path)
        ref, ref_cpu = mitsuba_render(scene, args.ref_spp, 1000)
        ref_mean = ref.reshape(-1, 3).mean(0)
        mi_err, mi_cpu, om_err, om_s, om_means = [], 0.0, [], 0.0, []
        mi_trim, om_trim = [], []
        warnings = ""
        for s in range(args.seeds):
            img, cpu = mitsuba_render(scene, args.spp, s + 1)
            mi_err.append(relmse(img, ref, args.eps))
            mi_trim.append(relmse(img, ref, args.eps, 0.001))
            mi_cpu += cpu
            img, secs, stderr = omis_render(args.omis, path, args.spp, s + 1,
                                            os.path.join(work, f"{name}-{s}.exr"))
            om_err.append(relmse(img, ref, args.eps))
            om_trim.append(relmse(img, ref, args.eps, 0.001))
            om_s += secs
            om_means.append(img.reshape(-1, 3).mean(0))
            warnings = stderr
        om_mean = np.mean(om_means, axis=0)
        dev = np.abs(om_mean - ref_mean) / np.maximum(np.abs(ref_mean), 1e-6)
        ratio = np.mean(om_err) / max(np.mean(mi_err), 1e-12)
        ok = bool(np.all(dev <= args.mean_tol)) and ratio <= args.ratio
        trimmed = np.mean(om_trim) / max(np.mean(mi_trim), 1e-12)
        rows.append((name, ref_mean, om_mean, dev.max(), np.mean(mi_err), np.mean(om_err), ratio,
                     trimmed,
                     mi_cpu / args.seeds / args.spp, om_s / args.seeds / args.spp, ok))
        if not ok:
            failed.append(name)
            if warnings.strip():
                print(f"{name}: omis said:\n{warnings.strip()}", file=sys.stderr)
    print(f"Mitsuba {mi.__version__} scalar_rgb reference at {args.ref_spp} spp; {args.seeds} seeds "
          f"at {args.spp} spp; relMSE eps {args.eps}")
    print("| scene | Mitsuba 3 mean (R, G, B) | omis mean | worst channel | relMSE Mitsuba 3 | "
          "relMSE omis | ratio | ratio w/o 0.1 % worst pixels | s/spp Mitsuba 3 scalar (CPU) | "
          "s/spp omis (wall, 2 threads) | |")
    print("|---|---|---|---:|---:|---:|---:|---:|---:|---:|---|")
    for (n, rm, om, dev, me, oe, ratio, trimmed, mt, ot, ok) in rows:
        fmt = lambda v: ", ".join(f"{x:.4f}" for x in v)
        print(f"| {n} | {fmt(rm)} | {fmt(om)} | {100 * dev:.2f} % | {me:.5f} | {oe:.5f} | "
              f"{ratio:.2f}x | {trimmed:.2f}x | {mt:.4f} | {ot:.4f} | {'ok' if ok else 'FAILED'} |")
    if failed:
        print(f"failed: {', '.join(failed)}", file=sys.stderr)
        sys.exit(1)


if __name__ == "__main__":
    main()
