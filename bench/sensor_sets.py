"""What each extra IMU set is worth, on the validation split, in one run (the variable-sensor-set issue).

    python bench/sensor_sets.py --data ../shared/mocap [--models DIR] [--baseline DIR] [--out out/sensor_sets]
        [--people unseen|seen] [--no-heading | --heading-settings JSON] [--perfect-heading] [--body NAME]

Runs edge eval at N=1 (int8 by default) with no extra IMUs, both feet, both shins, thighs and shins, and all seven,
each steady and with DragPoser's faulty-sensor protocol (--faults disconnect), two evals at a time; with
--baseline, also every set of another model folder (e.g. the previously shipped one). Prints one table
for the people the model never saw (val subjects with no clip in train: what choices are made on) and
one for the people it saw, each set steady, under the protocol, and the protocol against the set
steady and against no extra IMUs at all (a flaky tracker must never be worse than none: <= 1.00);
writes every eval's JSON. Takes a few minutes on 2 cores. The extra
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
from bench.cached import run_cached
from edge.imus import ImuNoise, parse_set
from edge.inference import DEFAULT_PRECISION

SETS = {"none": "none", "feet": "l_foot,r_foot", "shins": "l_shin,r_shin", "thighs+shins": "l_thigh,r_thigh,l_shin,r_shin",
        "all seven": "all"}
LIMITS = {"shins": 0.85, "thighs+shins": 0.65, "all seven": 0.42}     # mpjpe against the `none` figure


def _run(job):
    name, path, kwargs = job
    return name, run_cached((path, {**kwargs, "keep_per_clip": True}))


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
    ap.add_argument("--people", choices=("unseen", "seen"), default=None,
                    help="evaluate only unseen (or seen) people's clips (default: all, reported apart)")
    ap.add_argument("--max-clips", type=int, default=None, help="an even spread of this many val clips (a quick look)")
    ap.add_argument("--no-disconnect", action="store_true", help="skip the faulty-sensor runs")
    ap.add_argument("--leg-guard", type=float, default=None,
                    help="the foot IK's leg clearance in m (edge.ik.guard_legs; 0: off; default the runtime's)")
    ap.add_argument("--conventions", choices=("out", "in"), default="out",
                    help="score against val retargeted with the sources' skeleton conventions taken out (today's "
                         "ruler, motion.neutrals) or left in (the ruler before it, v0.5.1's published figures)")
    ap.add_argument("--body", help="the sets on one of `edge eval --bodies standard`'s bodies (its name, e.g. "
                                   "'1.55 m, long legs') instead of the canonical one (#54)")
    a = ap.parse_args()
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    refine = {"steps": a.refine_steps, **({"terms": a.refine_terms.split(",")} if a.refine_terms else {})} if a.refine else None
    heading = False if a.no_heading else (json.loads(a.heading_settings) if a.heading_settings else True)
    options = PipelineOptions(samples=a.samples, precision=a.precision, refine=refine, heading=heading)
    if a.leg_guard is not None:
        options = replace(options, leg_guard=a.leg_guard)
    common = {"data": a.data, "options": options, "max_clips": a.max_clips, "people": a.people,
              "conventions": a.conventions == "out"}
    if a.body:
        from motion.bodies import standard_bodies
        named = {b.name: b for b in standard_bodies()}
        if a.body not in named:
            ap.error(f"--body {a.body!r}: one of {', '.join(repr(n) for n in named)}")
        common["body"] = named[a.body]
    if a.perfect_heading:
        common["imu_noise"] = ImuNoise(yaw_offset_std_deg=0.0, yaw_drift_deg_s=0.0)
    jobs = []
    for tag, models in (("", a.models), ("baseline ", a.baseline)):
        if tag and not models:
            continue
        for name, spec in SETS.items():
            slug = tag.replace(" ", "_") + name.replace(" ", "_").replace("+", "_")
            jobs.append((tag + name, out / f"{slug}.json", {**common, "models": models, "trackers": parse_set(spec)}))
            if spec != "none" and not a.no_disconnect:
                jobs.append((tag + name + " disconnect", out / f"{slug}_disconnect.json",
                             {**common, "models": models, "trackers": parse_set(spec), "faults": "disconnect"}))
    with ProcessPoolExecutor(a.jobs) as ex:
        runs = dict(ex.map(_run, jobs))
    rows = {}
    for who in ("unseen", "seen"):
        part = {name: r["people"][who] for name, r in runs.items() if who in r.get("people", {})}
        if "none" not in part:
            continue
        print(f"\nval, {who} people, N={a.samples}, {a.precision}: {part['none']['clips']} clips, "
              f"{part['none']['frames']} frames")
        rows[who] = table(part, "baseline none" in part)
    (out / "summary.json").write_text(json.dumps(rows, indent=2) + "\n")
    print(f"wrote {out}/")


def table(part, with_baseline):
    """Print one group's table and return its rows: each set steady (mpjpe, knees, ankles, against no
    extra IMUs, skate), under DragPoser's protocol, that against the set steady and against none."""
    print(f"{'set':<22} {'mpjpe cm':>9} {'knees':>6} {'ankles':>6} {'x none':>7} {'limit':>6} {'skate':>6} "
          f"{'flaky cm':>9} {'x steady':>8} {'x none':>7}" + ("  baseline: mpjpe  flaky" if with_baseline else ""))
    rows, none = {}, part["none"]["mpjpe_cm"]
    for name in SETS:
        r, d = part[name], part.get(name + " disconnect")
        b, bd = part.get("baseline " + name), part.get("baseline " + name + " disconnect")
        print(f"{name:<22} {r['mpjpe_cm']:9.3f} {r['knees_cm']:6.2f} {r['ankles_cm']:6.2f} {r['mpjpe_cm'] / none:7.3f} "
              f"{LIMITS.get(name, ''):>6} {r['foot_skate_cm_s']:6.2f}"
              + (f" {d['mpjpe_cm']:9.3f} {d['mpjpe_cm'] / r['mpjpe_cm']:8.3f} {d['mpjpe_cm'] / none:7.3f}" if d else " " * 27)
              + (f"  {b['mpjpe_cm']:14.3f}" if b else "") + (f" {bd['mpjpe_cm']:6.3f}" if bd else ""))
        rows[name] = {"mpjpe_cm": r["mpjpe_cm"], "knees_cm": r["knees_cm"], "ankles_cm": r["ankles_cm"],
                      "ratio_to_none": r["mpjpe_cm"] / none, "foot_skate_cm_s": r["foot_skate_cm_s"],
                      "leg_intersect_rate": r["leg_intersect_rate"], "float_rate": r["float_rate"],
                      "disconnect_mpjpe_cm": d["mpjpe_cm"] if d else None,
                      "disconnect_ratio": d["mpjpe_cm"] / r["mpjpe_cm"] if d else None,
                      "disconnect_ratio_to_none": d["mpjpe_cm"] / none if d else None,
                      "baseline_mpjpe_cm": b["mpjpe_cm"] if b else None,
                      "baseline_disconnect_mpjpe_cm": bd["mpjpe_cm"] if bd else None}
    return rows


if __name__ == "__main__":
    main()
