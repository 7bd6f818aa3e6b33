"""Per-frame cost of the whole SSI pipeline against the bare decoder call, at several N, in one run.

    python bench/pipeline.py [--samples 1,10,32,100] [--frames 600] [--precision fp32] [--json OUT]

Pins itself to one core (like the board's budget) and reports medians and p99 in microseconds, and
the pipeline / decoder ratio. A benchmark, not a test: it prints figures and asserts nothing.
"""
import argparse
import json
import sys
import os
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from edge.pipeline import Pipeline
from edge.takes import from_sample
from edge.timing import time_calls

SAMPLE = Path(__file__).resolve().parent.parent / "samples" / "cmu_09_12_walk.npz"


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--samples", default="1,10,32,100")
    ap.add_argument("--frames", type=int, default=600)
    ap.add_argument("--precision", default="fp32")
    ap.add_argument("--json")
    a = ap.parse_args()
    try:
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
    except (AttributeError, OSError):
        pass
    take = from_sample(SAMPLE)
    frames = [take.signals.slice(t, t + 1) for t in range(take.frames)]
    rows = []
    print(f"{'N':>4} {'pipeline p50':>13} {'p99':>8} {'decoder p50':>12} {'p99':>8} {'ratio':>6}   (microseconds, one core)")
    for n in [int(x) for x in a.samples.split(",")]:
        pipe = Pipeline(samples=n, precision=a.precision)
        for t in range(120):
            pipe.step(frames[t % len(frames)])
        whole = time_calls(lambda i: pipe.step(frames[(i + 120) % len(frames)]), a.frames)
        bare = time_calls(lambda i: pipe.decoder.step(), a.frames)
        r = {"samples": n, "pipeline_us": {"p50": float(np.median(whole)), "p99": float(np.percentile(whole, 99))},
             "decoder_us": {"p50": float(np.median(bare)), "p99": float(np.percentile(bare, 99))}}
        r["ratio_p50"] = r["pipeline_us"]["p50"] / r["decoder_us"]["p50"]
        rows.append(r)
        print(f"{n:>4} {r['pipeline_us']['p50']:>13.0f} {r['pipeline_us']['p99']:>8.0f} "
              f"{r['decoder_us']['p50']:>12.0f} {r['decoder_us']['p99']:>8.0f} {r['ratio_p50']:>6.2f}")
    if a.json:
        Path(a.json).write_text(json.dumps({"precision": a.precision, "results": rows}, indent=2) + "\n")


if __name__ == "__main__":
    main()
