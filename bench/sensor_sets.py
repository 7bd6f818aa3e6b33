"""What each extra IMU set is worth, on the validation split, in one run (the variable-sensor-set issue).

    python bench/sensor_sets.py --data ../shared/mocap [--models DIR] [--baseline DIR] [--out out/sensor_sets]
        [--no-heading | --heading-settings JSON] [--perfect-heading]

Runs edge eval at N=1 (int8 by default) with no extra IMUs, both shins, thighs and shins, and all seven,
each clean and with DragPoser's faulty-sensor protocol (--faults disconnect), two evals at a time; with
--baseline, also the 4-point case of another model folder (e.g. the previously shipped one). Prints the
table of the issue's lines and writes every eval's JSON. Takes about a minute on 2 cores. The extra
IMUs' heading observer (edge.heading) runs, as it does by default; --no-heading turns it off;
--perfect-heading takes the heading offset and drift out of the IMU noise instead (the most an
observer could give).
"""
import argparse
from dataclasses import replace
import json
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from edge.options import PipelineOptions
from motion.evaluate import evaluate
from edge.imus import ImuNoise, parse_set
from edge.inference import DEFAULT_PRECISION

SETS = {"none": "none", "shins": "l_shin,r_shin", "thighs+shins": "l_thigh,r_thigh,l_shin,r_shin", "all seven": "all"}
LIMITS = {"shins": 0.85, "thighs+shins": 0.65, "all seven": 0.42}     # mpjpe against the `none` figure


def _run(job):
    name, path, kwargs = job
    if Path(path).exists():
        return name, json.loads(Path(path).read_text())
    r = evaluate([kwargs.pop("data")], kwargs.pop("options"), split="val", log=lambda *a: None, **kwargs)
    Path(path).write_text(json.dumps(r, indent=2) + "\n")
    return name, r


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default="../shared/mocap")
    ap.add_argument("--models", help="the model folder to measure (default: the shipped models/)")
    ap.add_argument("--baseline", help="another model folder whose 4-point case to measure beside it")
    ap.add_argument("--precision", choices=("fp32", "int8"), default=DEFAULT_PRECISION)
    ap.add_argument("--samples", type=int, default=1)
    ap.add_argument("--out", default="out/sensor_sets")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--refine", action="store_true", help="with latent refinement (edge.refine) at its defaults")
    ap.add_argument("--refine-terms", default=None, help="comma-separated refinement terms (default all)")
    ap.add_argument("--refine-steps", type=int, default=2)
    ap.add_argument("--no-heading", action="store_true", help="without the extra IMUs' heading observer (edge.heading)")
    ap.add_argument("--heading-settings", default=None, help="its settings as JSON (a choosing run), e.g. '{\"measurement_std_deg\": 5}'")
    ap.add_argument("--perfect-heading", action="store_true",
                    help="IMU noise without its heading offset and drift (what a perfect heading observer would leave)")
    ap.add_argument("--max-clips", type=int, default=None, help="an even spread of this many val clips (a quick look)")
    ap.add_argument("--no-disconnect", action="store_true", help="skip the faulty-sensor runs")
    ap.add_argument("--leg-guard", type=float, default=None,
                    help="the foot IK's leg clearance in m (edge.ik.guard_legs; 0: off; default the runtime's)")
    a = ap.parse_args()
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    refine = {"steps": a.refine_steps, **({"terms": a.refine_terms.split(",")} if a.refine_terms else {})} if a.refine else None
    heading = False if a.no_heading else (json.loads(a.heading_settings) if a.heading_settings else True)
    options = PipelineOptions(samples=a.samples, precision=a.precision, refine=refine, heading=heading)
    if a.leg_guard is not None:
        options = replace(options, leg_guard=a.leg_guard)
    common = {"data": a.data, "options": options, "max_clips": a.max_clips}
    if a.perfect_heading:
        common["imu_noise"] = ImuNoise(yaw_offset_std_deg=0.0, yaw_drift_deg_s=0.0)
    jobs = []
    if a.baseline:
        jobs.append(("baseline none", out / "baseline_none.json", {**common, "models": a.baseline}))
    for name, spec in SETS.items():
        slug = name.replace(" ", "_").replace("+", "_")
        jobs.append((name, out / f"{slug}.json", {**common, "models": a.models, "trackers": parse_set(spec)}))
        if spec != "none" and not a.no_disconnect:
            jobs.append((name + " disconnect", out / f"{slug}_disconnect.json",
                         {**common, "models": a.models, "trackers": parse_set(spec), "faults": "disconnect"}))
    with ProcessPoolExecutor(a.jobs) as ex:
        runs = dict(ex.map(_run, jobs))
    none = runs["none"]
    print(f"val, N={a.samples}, {a.precision}: {none['clips']} clips, {none['frames']} frames")
    print(f"{'set':<28} {'mpjpe cm':>9} {'x none':>7} {'limit':>6} {'skate cm/s':>11} {'disc. mpjpe':>12} {'x clean':>8}")
    rows = {}
    if "baseline none" in runs:
        b = runs["baseline none"]
        print(f"{'baseline model, none':<28} {b['mpjpe_cm']:9.3f} {b['mpjpe_cm'] / none['mpjpe_cm']:7.3f} {'':>6} "
              f"{b['foot_skate_cm_s']:11.2f}")
        rows["baseline none"] = b["mpjpe_cm"]
    for name in SETS:
        r = runs[name]
        d = runs.get(name + " disconnect")
        ratio = r["mpjpe_cm"] / none["mpjpe_cm"]
        print(f"{name:<28} {r['mpjpe_cm']:9.3f} {ratio:7.3f} {LIMITS.get(name, ''):>6} {r['foot_skate_cm_s']:11.2f}"
              + (f" {d['mpjpe_cm']:12.3f} {d['mpjpe_cm'] / r['mpjpe_cm']:8.3f}" if d else ""))
        rows[name] = {"mpjpe_cm": r["mpjpe_cm"], "ratio_to_none": ratio, "foot_skate_cm_s": r["foot_skate_cm_s"],
                      "disconnect_mpjpe_cm": d["mpjpe_cm"] if d else None,
                      "disconnect_ratio": d["mpjpe_cm"] / r["mpjpe_cm"] if d else None}
    (out / "summary.json").write_text(json.dumps(rows, indent=2) + "\n")
    print(f"wrote {out}/")


if __name__ == "__main__":
    main()
