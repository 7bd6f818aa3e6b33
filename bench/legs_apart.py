"""The body in the present, measured on val: what keeps the legs apart at tau = 0 (issue #30's lines).

    python bench/legs_apart.py [--data ../shared/mocap] [--samples 1,16,32] [--clearances 0.14]
                               [--seeds 0] [--precision int8] [--out out/legs_apart] [--jobs 2]
                               [--models DIR]

For each N: the plain run (N=1; N > 1 with --no-ssi), SSI without LegsApart (refinement's guards only:
what the board ran before), and SSI with LegsApart at each --clearance (the board's default
refinement; edge.refine.LegsApart); at N=1 the plain run and LegsApart. Each is an `edge eval` of all
of val at the look-ahead the board uses (0), once per --seeds draw of the latents. Prints mpjpe and
foot skate against N=1's, and floor + leg-crossing faults (penetration_rate + leg_intersect_rate)
against the same N's plain run. Evals already in --out are reused. About 40 s an eval on 2 cores.
"""
import argparse
import sys
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from edge.inference import DEFAULT_PRECISION
from edge.options import PipelineOptions
from edge.refine import DEFAULT_TERMS, LegsApart, RefineSettings
from bench.cached import run_cached

GUARDS_ONLY = tuple(t for t in DEFAULT_TERMS if t != "legs")


def variants(N, clearances, seed, precision):
    """(name, PipelineOptions) of the runs for one N and latent draw."""
    base = PipelineOptions(samples=N, seed=seed, precision=precision, lookahead=0)
    legs = [(f"legs {c:.2f}", replace(base, refine=RefineSettings(
        terms=tuple(t if t != "legs" else LegsApart(clearance=c) for t in DEFAULT_TERMS)))) for c in clearances]
    if N == 1:
        return [("plain", base)] + legs
    return ([("no SSI", replace(base, ssi=False)),
             ("SSI, guards only", replace(base, refine=RefineSettings(terms=GUARDS_ONLY)))]
            + [(f"SSI, {name}", o) for name, o in legs])


def faults(r):
    return r["penetration_rate"] + r["leg_intersect_rate"]


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="../shared/mocap")
    ap.add_argument("--samples", default="1,16,32")
    ap.add_argument("--clearances", default="0.14", help="LegsApart clearances (m), comma-separated")
    ap.add_argument("--seeds", default="0", help="latent draws, comma-separated")
    ap.add_argument("--precision", choices=("fp32", "int8"), default=DEFAULT_PRECISION)
    ap.add_argument("--out", default="out/legs_apart")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--models", help="the model folder (default: the shipped models/); use its own --out")
    a = ap.parse_args()
    if not Path(a.data).is_dir():
        sys.exit(f"bench/legs_apart.py: no motion data at {a.data} (it needs ../shared/mocap's val split)")
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    Ns = sorted({1, *(int(n) for n in a.samples.split(","))})
    clearances = [float(c) for c in a.clearances.split(",")]
    seeds = [int(s) for s in a.seeds.split(",")]
    jobs = []
    for N in Ns:
        for seed in seeds if N > 1 else [0]:
            for name, o in variants(N, clearances, seed, a.precision):
                slug = name.replace(", ", "-").replace(" ", "_")
                jobs.append((N, seed, name, (str(out / f"N{N}-s{seed}-{slug}-{a.precision}.json"), a.data, o, a.models)))
    with ProcessPoolExecutor(a.jobs) as pool:
        results = list(pool.map(run_cached, [(path, {"data": data, "options": options, "models": models}) for *_, (path, data, options, models) in jobs]))
    rows = {(N, seed, name): r for (N, seed, name, _), r in zip(jobs, results, strict=True)}
    one = rows[(1, 0, "plain")]
    print(f"val, {a.precision}, tau = 0; N=1: mpjpe {one['mpjpe_cm']:.3f} cm, skate {one['foot_skate_cm_s']:.2f} cm/s, "
          f"faults {100 * faults(one):.3f} %")
    print("| N | seed | variant | mpjpe cm | x N=1 | skate cm/s | x N=1 | faults | x plain | switches |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for (N, seed, name), r in rows.items():
        plain = rows[(N, seed, "plain" if N == 1 else "no SSI")]
        print(f"| {N} | {seed} | {name} | {r['mpjpe_cm']:.3f} | {r['mpjpe_cm'] / one['mpjpe_cm']:.3f} | "
              f"{r['foot_skate_cm_s']:.2f} | {r['foot_skate_cm_s'] / one['foot_skate_cm_s']:.3f} | "
              f"{100 * faults(r):.3f} % | {faults(r) / max(faults(plain), 1e-12):.2f} | {r['ssi_switches']} |")


if __name__ == "__main__":
    main()
