"""The per-frame cost of two checkouts of this repository, interleaved: did a change move the figures?

    git worktree add /tmp/before <rev>
    python bench/before_after.py --before /tmp/before [--after .] [--rounds 8] [--samples 100] [--frames 400]

Each round runs `bench/pipeline.py` (the plain run: the whole pipeline, then its bare decoder call, at
N = --samples, pinned to one core) once per checkout and precision (int8, fp32), in an order that
alternates round by round, each checkout in its own process on its own code. Machine noise then hits
both sides alike. Printed per precision: each side's median over the rounds of the pipeline p50, the
decoder p50 and their ratio, and after / before with the range of the per-round ratios (the noise).
A benchmark, not a test: it prints figures and asserts nothing.
"""
import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent.parent


def one_run(tree, precision, samples, frames):
    """bench/pipeline.py in `tree` (its own code first on the path) -> (pipeline p50, decoder p50) in us."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "run.json"
        env = dict(os.environ, PYTHONPATH=str(tree))
        subprocess.run([sys.executable, str(Path(tree) / "bench" / "pipeline.py"), "--samples", str(samples),
                        "--frames", str(frames), "--precision", precision, "--json", str(out)],
                       cwd=tree, env=env, check=True, capture_output=True, text=True, timeout=900)
        r = json.loads(out.read_text())["results"][0]
    return r["pipeline_us"]["p50"], r["decoder_us"]["p50"]


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--before", required=True, help="a checkout of the earlier revision (git worktree add)")
    ap.add_argument("--after", default=str(HERE))
    ap.add_argument("--rounds", type=int, default=8)
    ap.add_argument("--samples", type=int, default=100)
    ap.add_argument("--frames", type=int, default=400)
    ap.add_argument("--json")
    a = ap.parse_args()
    trees = {"before": Path(a.before).resolve(), "after": Path(a.after).resolve()}
    runs = {(side, p): [] for side in trees for p in ("int8", "fp32")}
    for k in range(a.rounds):
        order = list(trees) if k % 2 == 0 else list(trees)[::-1]
        for p in ("int8", "fp32"):
            for side in order:
                runs[side, p].append(one_run(trees[side], p, a.samples, a.frames))
        print(f"round {k + 1}/{a.rounds}: " + "  ".join(f"{s} {p} {runs[s, p][-1][0]:.0f}/{runs[s, p][-1][1]:.0f} us"
                                                      for p in ("int8", "fp32") for s in trees), file=sys.stderr)
    report = {"samples": a.samples, "frames": a.frames, "rounds": a.rounds,
              "trees": {k: str(v) for k, v in trees.items()}, "precisions": {}}
    print(f"N={a.samples}, {a.rounds} interleaved rounds of {a.frames} frames; medians over rounds (microseconds)")
    print(f"{'':6} {'side':>7} {'pipeline':>9} {'decoder':>8} {'ratio':>6}")
    for p in ("int8", "fp32"):
        b, f = np.array(runs["before", p]), np.array(runs["after", p])
        per_round = {"pipeline": f[:, 0] / b[:, 0], "ratio": (f[:, 0] / f[:, 1]) / (b[:, 0] / b[:, 1])}
        row = {}
        for side, x in (("before", b), ("after", f)):
            row[side] = {"pipeline_us": float(np.median(x[:, 0])), "decoder_us": float(np.median(x[:, 1])),
                         "ratio": float(np.median(x[:, 0] / x[:, 1]))}
            print(f"{p:6} {side:>7} {row[side]['pipeline_us']:9.0f} {row[side]['decoder_us']:8.0f} "
                  f"{row[side]['ratio']:6.3f}")
        row["after_over_before"] = {k: {"median": float(np.median(v)), "min": float(v.min()), "max": float(v.max())}
                                    for k, v in per_round.items()}
        for k, v in row["after_over_before"].items():
            print(f"{p:6} after/before {k:9} {v['median']:.3f} (rounds {v['min']:.3f} .. {v['max']:.3f})")
        report["precisions"][p] = row
    if a.json:
        Path(a.json).write_text(json.dumps(report, indent=2) + "\n")


if __name__ == "__main__":
    main()
