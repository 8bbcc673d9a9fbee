"""Pipeline throughput: alignment → clustering on terminal-area (200 aircraft, 4 radars, 1 h).

In a fresh process per repetition: simulate (not timed), then time each stage of
``tertiary.pipeline.process`` without trackers (validation, alignment, association, fusion
with every method, the centralised reference, clustering, evaluation) and record reports/s through
alignment → clustering and the peak resident memory reached by the end of clustering (it
includes the simulated dataset held in memory). Target: ≥ 500 000 reports/s, < 2 GB.

    python benchmarks/bench_pipeline.py [--repeat 2] [--aircraft 200] [--duration 3600]
"""

from __future__ import annotations

import argparse
import json
import statistics

from _util import record, run_isolated

CODE = """
import json, time, dataclasses, resource
from tertiary.simulate import load_scenario, simulate
from tertiary import pipeline
cfg = load_scenario("terminal-area")
cfg = dataclasses.replace(cfg, duration_s={duration}, traffic=dataclasses.replace(cfg.traffic, aircraft={aircraft}))
ds = simulate(cfg)
peak = {{}}
def mark(stage):  # peak RSS so far, read when each stage starts
    peak[stage] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
res = pipeline.process(ds, pipeline.PipelineConfig(filters=()), progress=mark)
print(json.dumps({{"reports": ds.reports.height, "timings": res.timings, "counts": res.counts,
                  "peak_rss_mib_after_simulate": peak["validate"],
                  "peak_rss_mib_alignment_to_clustering": peak["track"]}}))
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--aircraft", type=int, default=200)
    ap.add_argument("--duration", type=float, default=3600.0)
    args = ap.parse_args()
    runs = [run_isolated(CODE.format(aircraft=args.aircraft, duration=args.duration)) for _ in range(args.repeat)]
    best = min(runs, key=lambda r: r["timings"]["alignment_to_clustering_s"])
    wall = best["timings"]["alignment_to_clustering_s"]
    result = {
        "scenario": {"aircraft": args.aircraft, "radars": 4, "duration_s": args.duration},
        "reports": best["reports"],
        "alignment_to_clustering_s_best": wall,
        "alignment_to_clustering_s_median": statistics.median(r["timings"]["alignment_to_clustering_s"] for r in runs),
        "reports_per_s_best": best["reports"] / wall,
        "stage_s_best": {k: round(v, 3) for k, v in best["timings"].items()},
        "counts": best["counts"],
        "peak_rss_mib_alignment_to_clustering": max(r["peak_rss_mib_alignment_to_clustering"] for r in runs),
        "peak_rss_mib_after_simulate": max(r["peak_rss_mib_after_simulate"] for r in runs),
        "peak_rss_mib_with_evaluation": max(r["peak_rss_mib"] for r in runs),
        "targets": {"reports_per_s": 500_000, "peak_rss_mib": 2048},
    }
    path = record("bench_pipeline", result)
    print(json.dumps(result, indent=2))
    print(f"recorded in {path}")


if __name__ == "__main__":
    main()
