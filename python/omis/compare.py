"""`compare`: MIS strategies against a reference at equal spp and/or equal time, through the
service (the experiment of `omis compare`, after Cailleau et al., "Optimal Multiple Importance
Sampling for Bidirectional Path Tracing"): a table and its plots."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Optional, Sequence

from .client import Client, Reference, Scene, SeriesPoint


@dataclass
class CompareResult:
    """The runs of a comparison: one record per (experiment, mis, spp or budget, seed)."""

    #: One dict per job: experiment (``equal_spp`` / ``equal_time``), mis, seed, spp_target,
    #: time_budget_s, spp (merged), seconds (the job's elapsed time), relmse, job (its id).
    records: list[dict[str, Any]]
    #: Per record (same order), the job's relMSE after each merged pass.
    series: list[list[SeriesPoint]] = field(default_factory=list)

    @property
    def df(self) -> Any:
        """The records as a pandas DataFrame, or None when pandas is not installed."""
        try:
            import pandas as pd
        except ImportError:
            return None
        return pd.DataFrame.from_records(self.records)

    def mean_relmse(self, experiment: str) -> dict[str, list[tuple[float, float]]]:
        """Per mis: (spp or time budget, relMSE averaged over seeds), sorted."""
        key = "spp_target" if experiment == "equal_spp" else "time_budget_s"
        acc: dict[str, dict[float, list[float]]] = {}
        for r in self.records:
            if r["experiment"] == experiment and r["relmse"] is not None:
                acc.setdefault(r["mis"], {}).setdefault(float(r[key]), []).append(r["relmse"])
        return {
            m: sorted((x, sum(v) / len(v)) for x, v in pts.items()) for m, pts in acc.items()
        }

    def plots(self) -> dict[str, Any]:
        """matplotlib figures: ``relmse_vs_spp`` (equal spp, mean over seeds, log-log) and
        ``relmse_vs_time`` (equal time: every job's relMSE after each pass against its
        seconds, log-log). Needs matplotlib."""
        import matplotlib.pyplot as plt
        from matplotlib.ticker import NullFormatter

        def finish(fig: Any, ax: Any, xlabel: str, title: str) -> None:
            # Labels on the decades only: minor labels of a short log axis overlap.
            ax.xaxis.set_minor_formatter(NullFormatter())
            ax.yaxis.set_minor_formatter(NullFormatter())
            ax.set_xlabel(xlabel)
            ax.set_ylabel("relMSE")
            ax.set_title(title)
            ax.legend()
            fig.tight_layout()

        figs: dict[str, Any] = {}
        spp = self.mean_relmse("equal_spp")
        if spp:
            fig, ax = plt.subplots(figsize=(5, 3.5))
            for m, pts in spp.items():
                ax.loglog([p[0] for p in pts], [p[1] for p in pts], "o-", label=m)
            finish(fig, ax, "samples per pixel", "equal spp")
            figs["relmse_vs_spp"] = fig
        timed = [
            (r, s)
            for r, s in zip(self.records, self.series)
            if r["experiment"] == "equal_time"
        ]
        if timed:
            fig, ax = plt.subplots(figsize=(5, 3.5))
            colors: dict[str, Any] = {}
            for r, s in timed:
                pts = [(p.seconds, p.relmse) for p in s if p.relmse is not None and p.seconds > 0]
                if not pts:
                    continue
                label = None if r["mis"] in colors else r["mis"]
                (line,) = ax.loglog(
                    [p[0] for p in pts], [p[1] for p in pts], "o-", label=label,
                    color=colors.get(r["mis"]),
                )
                colors.setdefault(r["mis"], line.get_color())
            finish(fig, ax, "seconds", "equal time")
            figs["relmse_vs_time"] = fig
        return figs


def compare(
    scene: Scene,
    reference: Reference,
    mis: Sequence[str] = ("balance", "power", "optimal"),
    spp: Optional[Sequence[int]] = None,
    equal_time: Optional[float] = None,
    seeds: int = 1,
    *,
    client: Optional[Client] = None,
    integrator: str = "bdpt",
    progress: bool = False,
    timeout: Optional[float] = None,
    **settings: Any,
) -> CompareResult:
    """Renders `scene` with each MIS strategy in `mis` at each spp of `spp` and/or for
    `equal_time` seconds each, with `seeds` seeds (0, 1, ...), against `reference` (an EXR
    path, an array or a finished `Job`); jobs run one after another so that their times are
    comparable. `settings` go to every job (``resolution``, ``max_depth``, ...). Returns the
    records (and `CompareResult.df`, `CompareResult.plots`)."""
    if not spp and equal_time is None:
        raise ValueError("give spp=[...] and/or equal_time=seconds")
    from .api import default_client

    c = client or default_client()
    ref = c.reference_source(reference)
    runs: list[tuple[str, dict[str, Any]]] = []
    for m in mis:
        for n in spp or ():
            runs.append(("equal_spp", {"mis": m, "spp": int(n)}))
        if equal_time is not None:
            runs.append(("equal_time", {"mis": m, "time_budget_s": float(equal_time)}))
    result = CompareResult(records=[])
    for experiment, run in runs:
        for seed in range(seeds):
            job = c.submit(
                scene,
                reference=ref,
                name=f"compare {experiment} {run['mis']} seed {seed}",
                **{**settings, "integrator": integrator, "seed": seed, **run},
            )
            st = job.wait(progress=progress, timeout=timeout)
            result.records.append(
                {
                    "experiment": experiment,
                    "mis": run["mis"],
                    "seed": seed,
                    "spp_target": run.get("spp"),
                    "time_budget_s": run.get("time_budget_s"),
                    "spp": st["spp_done"],
                    "seconds": st["elapsed_s"],
                    "relmse": st["relmse"],
                    "job": job.id,
                }
            )
            result.series.append(job.relmse_series())
    return result
