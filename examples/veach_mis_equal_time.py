#!/usr/bin/env python3
"""Veach's MIS scene with BDPT: balance heuristic against optimal MIS at equal time.

Renders a reference (BDPT, balance, many samples), then each strategy for the same number of
seconds, and plots relMSE against time (one point per merged pass). Writes to --out:
reference.exr, balance.exr, optimal.exr, images.png (the three side by side), relmse_vs_time.png,
results.csv. Runs on an embedded coordinator (the omis binary from --binary, OMIS_BIN or PATH),
or on a running one with --server.

    pip install ./python matplotlib
    python examples/veach_mis_equal_time.py --out veach-out --seconds 10
    python examples/veach_mis_equal_time.py --out /tmp/v --quick     # a few seconds, tiny
"""

from __future__ import annotations

import argparse
import csv
import os
from pathlib import Path

import omis

SCENE = Path(__file__).resolve().parents[1] / "scenes" / "veach-mis.json"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("veach-mis-out"), help="output folder")
    ap.add_argument("--seconds", type=float, default=10.0, help="time per strategy")
    ap.add_argument("--reference-spp", type=int, default=1024)
    ap.add_argument("--resolution", default="320x180", help="WxH")
    ap.add_argument("--quick", action="store_true",
                    help="tiny settings for CI: 64x36, 1 s per strategy, 512 spp reference")
    ap.add_argument("--binary", help="the omis binary (default: OMIS_BIN, else PATH)")
    ap.add_argument("--server", help="a running coordinator's URL instead of an embedded one")
    ap.add_argument(
        "--client-token",
        dest="token",
        default=os.environ.get("OMIS_CLIENT_TOKEN") or os.environ.get("OMIS_TOKEN"),
    )
    ap.add_argument("--show", action="store_true", help="open the plots in a window")
    a = ap.parse_args()
    if a.quick:
        a.seconds, a.reference_spp, a.resolution = 1.0, 512, "64x36"
    w, h = (int(v) for v in a.resolution.lower().split("x"))
    a.out.mkdir(parents=True, exist_ok=True)

    import matplotlib.pyplot as plt

    settings = {"resolution": (w, h), "max_depth": 5, "pass_size": 1}
    with omis.Client(a.server, a.token, a.binary) as client:
        print(f"reference: bdpt balance, {a.reference_spp} spp at {w}x{h}")
        reference = client.submit(SCENE, integrator="bdpt", mis="balance",
                                  spp=a.reference_spp, seed=1000, name="veach reference",
                                  **settings)
        reference.wait(progress=not a.quick, timeout=3600)
        reference.download(a.out / "reference.exr")

        print(f"balance and optimal MIS, {a.seconds} s each")
        result = omis.compare(SCENE, reference, mis=["balance", "optimal"],
                              equal_time=a.seconds, seeds=1, client=client,
                              progress=not a.quick, timeout=a.seconds * 20 + 120, **settings)

        images = {"reference": reference.image()}
        for r in result.records:
            job = client.job(r["job"])
            job.download(a.out / f"{r['mis']}.exr")
            images[r["mis"]] = job.image()

    with open(a.out / "results.csv", "w", newline="") as f:
        out = csv.DictWriter(f, fieldnames=list(result.records[0]))
        out.writeheader()
        out.writerows(result.records)
    for r in result.records:
        print(f"{r['mis']:>8}: {r['spp']:5d} spp in {r['seconds']:.2f} s, "
              f"relMSE {r['relmse']:.4e}")

    figs = result.plots()
    figs["relmse_vs_time"].savefig(a.out / "relmse_vs_time.png", dpi=120)
    fig, axes = plt.subplots(1, len(images), figsize=(4 * len(images), 4 * h / w + 0.6))
    for ax, (name, img) in zip(axes, images.items()):
        ax.imshow(omis.tonemap(img))
        rel = "" if name == "reference" else f"\nrelMSE {omis.relmse(img, images['reference']):.3e}"
        ax.set_title(name + rel)
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(a.out / "images.png", dpi=120)
    print(f"wrote {a.out}/")
    if a.show:
        plt.show()


if __name__ == "__main__":
    main()
