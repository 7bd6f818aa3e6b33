"""Choose the SSI selection weights on val (the SSI-that-earns-its-samples issue).

    python bench/tune_selection.py --data ../shared/mocap [--samples 32] [--clips 48] [--weights 0,0.5,1,2,4]
                                   [--write] [--out out/tune_selection]

Runs edge eval at N (int8) on an even spread of --clips val clips with the autoencoder's score plus the
physical-plausibility criterion at each --weights value (0: the autoencoder alone), two at a time, and
N=1 on the same clips. Picks the weight with the smallest physical sum (penetration + leg intersection
+ float rates) whose mpjpe stays within 1.03 x N=1 and whose foot skate is no worse than N=1, prints the
table and, with --write, stores the choice in the model folder's manifest (`selection`).
"""
import argparse
import json
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from edge.options import PipelineOptions
from bench.cached import run_cached
from edge.modelfiles import DEFAULT_DIR


def selection(w):
    return {"plausibility": 1.0, **({"physical": {"weight": w, "floor": 1.0, "legs": 1.0, "support": 1.0}} if w else {})}


def physical(r):
    return r["penetration_rate"] + r["leg_intersect_rate"] + r["float_rate"]


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="../shared/mocap")
    ap.add_argument("--models", default=str(DEFAULT_DIR))
    ap.add_argument("--samples", type=int, default=32)
    ap.add_argument("--clips", type=int, default=48)
    ap.add_argument("--weights", default="0,0.5,1,2,4")
    ap.add_argument("--out", default="out/tune_selection")
    ap.add_argument("--write", action="store_true", help="store the chosen weights in the manifest")
    a = ap.parse_args()
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    ws = [float(x) for x in a.weights.split(",")]
    kw = {"data": a.data, "models": a.models, "max_clips": a.clips}
    jobs = [(out / "n1.json", {**kw, "options": PipelineOptions(samples=1)})] + [
        (out / f"w{w:g}.json", {**kw, "options": PipelineOptions(samples=a.samples, selection=selection(w))}) for w in ws]
    with ProcessPoolExecutor(2) as ex:
        n1, *runs = ex.map(run_cached, jobs)
    print(f"val subset: {n1['clips']} clips, {n1['frames']} frames; N=1 mpjpe {n1['mpjpe_cm']:.3f}, "
          f"skate {n1['foot_skate_cm_s']:.2f}, physical sum {physical(n1):.4f}")
    print(f"{'weight':>7} {'mpjpe':>7} {'skate':>7} {'pen':>7} {'legs':>7} {'float':>7} {'sum':>7} {'switches':>9}")
    best = None
    for w, r in zip(ws, runs, strict=True):
        ok = r["mpjpe_cm"] <= 1.03 * n1["mpjpe_cm"] and r["foot_skate_cm_s"] <= n1["foot_skate_cm_s"]
        print(f"{w:7g} {r['mpjpe_cm']:7.3f} {r['foot_skate_cm_s']:7.2f} {r['penetration_rate']:7.4f} "
              f"{r['leg_intersect_rate']:7.4f} {r['float_rate']:7.4f} {physical(r):7.4f} {r['ssi_switches']:>9}"
              + ("" if ok else "  (mpjpe or skate over the line)"))
        if ok and (best is None or physical(r) < best[1]):
            best = (w, physical(r))
    if best is None:
        print("no weight keeps mpjpe and skate within the lines")
        return
    print(f"chosen: physical weight {best[0]:g}")
    if a.write:
        path = Path(a.models) / "manifest.json"
        m = json.loads(path.read_text())
        m["selection"] = {**selection(best[0]), "chosen_on": f"val, {n1['clips']} clips, N={a.samples}, bench/tune_selection.py"}
        path.write_text(json.dumps(m, indent=2) + "\n")
        print(f"wrote the choice into {path}")


if __name__ == "__main__":
    main()
