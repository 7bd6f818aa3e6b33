"""Measure the SSI runtime against its targets on the validation split, in one run.

    python bench/ssi_check.py --data ../shared/mocap [--samples 32] [--runs 3] [--out out/ssi_check] [--models DIR]

Runs edge eval at N=1, at N with SSI and at N with --no-ssi (same seed), and the high-kick study at
N = 1, 10, 100, then prints each target with the measured figures. Takes tens of minutes on 2 cores.
"""
import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from edge.eval import evaluate
from edge.inference import DEFAULT_PRECISION
from edge.study import run_study


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="../shared/mocap")
    ap.add_argument("--samples", type=int, default=32)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--out", default="out/ssi_check")
    ap.add_argument("--skip-study", action="store_true")
    ap.add_argument("--models", help="model folder to check (default: the shipped models/)")
    ap.add_argument("--precision", choices=("fp32", "int8"), default=DEFAULT_PRECISION)
    a = ap.parse_args()
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    runs = {}
    for name, n, no_ssi in (("n1", 1, False), ("ssi", a.samples, False), ("no_ssi", a.samples, True)):
        path = out / f"eval_{name}.json"
        if path.exists():
            runs[name] = json.loads(path.read_text())
            continue
        runs[name] = evaluate([a.data], "val", samples=n, no_ssi=no_ssi, seed=0, models=a.models, precision=a.precision)
        path.write_text(json.dumps(runs[name], indent=2) + "\n")
    n1, ssi, base = runs["n1"], runs["ssi"], runs["no_ssi"]
    rows = [
        ("implausible_rate SSI <= 0.5 x no-SSI", ssi["implausible_rate"], 0.5 * base["implausible_rate"]),
        ("implausible_rate SSI <= N=1", ssi["implausible_rate"], n1["implausible_rate"]),
        ("mpjpe_cm SSI <= 1.05 x N=1", ssi["mpjpe_cm"], 1.05 * n1["mpjpe_cm"]),
        ("ee_error_cm <= 1.5", ssi["ee_error_cm"], 1.5),
        ("foot_skate_cm_s SSI <= N=1", ssi["foot_skate_cm_s"], n1["foot_skate_cm_s"]),
    ]
    tj = ssi["transition_jerk"]
    if tj["ratio"] is not None:
        rows.append(("peak jerk after switch <= 1.5 x quiet median", tj["peak_after_switch_mean_m_s3"],
                     1.5 * tj["peak_quiet_window_median_m_s3"]))
    if not a.skip_study:
        path = out / "study_high_kick.json"
        if path.exists():
            study = json.loads(path.read_text())
        else:
            study = run_study([a.data], "high-kick", [1, 10, 100], a.runs, split="val", models=a.models,
                              precision=a.precision)
            path.write_text(json.dumps(study, indent=2) + "\n")
        err = {r["samples"]: r["mean"] for r in study["results"]}
        rows.append(("high-kick N=10 <= 0.6 x N=1", err[10], 0.6 * err[1]))
        rows.append(("high-kick N=100 <= N=10", err[100], err[10]))
    print(f"\nN=1 / N={a.samples} SSI / N={a.samples} no-SSI on val:")
    for k in ("mpjpe_cm", "implausible_rate", "ee_error_cm", "foot_skate_cm_s", "jitter_m_s3", "ssi_switches"):
        print(f"  {k:18} {n1[k]:>10.4g} {ssi[k]:>10.4g} {base[k]:>10.4g}")
    print(f"  transition jerk: {tj}")
    print("\ntargets:")
    for name, value, limit in rows:
        print(f"  {'met ' if value <= limit else 'MISS'}  {name:48} {value:.4g} (limit {limit:.4g})")


if __name__ == "__main__":
    main()
