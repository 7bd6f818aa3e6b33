"""`edge eval`: reconstruction quality on BVH clips or sample files (motion.evaluate), written as JSON and
printed as one line."""
import json
import sys
from pathlib import Path

from edge.imus import parse_set
from edge.options import PipelineOptions
from motion.evaluate import evaluate


def refine_settings(args):
    """--refine [--refine-steps K] [--refine-terms a,b]: the Pipeline's refine= (None: off)."""
    if not getattr(args, "refine", False):
        return None
    out = {"steps": args.refine_steps}
    if args.refine_terms:
        out["terms"] = [t.strip() for t in args.refine_terms.split(",") if t.strip()]
    return out


def pipeline_options(args):
    """`edge eval`'s flags -> the PipelineOptions it evaluates."""
    return PipelineOptions(samples=args.samples, seed=args.seed, precision=args.precision, ssi=not args.no_ssi,
                           lookahead=args.lookahead, foot_ik=not args.no_ik, arm_ik=not args.no_ik,
                           segments=not args.no_segments, refine=refine_settings(args),
                           heading=not getattr(args, "no_heading", False))


def body_entry(body, result):
    """One body's line of `edge eval --bodies`: its errors in cm and as a share of its stature."""
    from edge.skeleton import JOINT
    per_joint = result["per_joint_mpjpe_cm"]
    return {**body.to_json(), "scale_to_canonical": round(result["height_scale"], 4),
            "clips": result["clips"], "frames": result["frames"], "mpjpe_cm": result["mpjpe_cm"],
            "mpjpe_pct_height": result["mpjpe_cm"] / body.height_m, "knees_cm": result["knees_cm"],
            "ankles_cm": result["ankles_cm"],
            "wrists_cm": (per_joint[JOINT["l_wrist"]] + per_joint[JOINT["r_wrist"]]) / 2,
            "penetration_rate": result["penetration_rate"], "foot_skate_cm_s": result["foot_skate_cm_s"]}


def evaluate_bodies(args, bodies):
    """The same clips on each body; the canonical body's full result, with "bodies" added."""
    import numpy as np

    from motion.bodies import measured_limbs
    from motion.evaluate import on_canonical_scale
    out, entries = None, []
    for k, body in enumerate(bodies):
        print(f"edge eval: body {body.name} ({body.height_m:.2f} m, legs {body.legs:g}x, arms {body.arms:g}x)",
              file=sys.stderr)
        measured = None
        if getattr(args, "body_measured", False):       # what edge calibrate's holds measure of this body
            measured = measured_limbs(body, np.random.default_rng([args.seed, k]))
        r = evaluate(args.data, pipeline_options(args), split=args.split, people=args.people, models=args.models,
                     trackers=parse_set(args.trackers), faults=args.faults, max_frames=args.max_frames,
                     max_clips=args.max_clips, body=body, body_known=getattr(args, "body_known", False),
                     limbs=measured[:2] if measured else None)
        r["height_scale"] = on_canonical_scale(body)
        entries.append(body_entry(body, r))
        if measured:
            entries[-1].update({"measured_legs": round(measured[0], 4), "measured_arms": round(measured[1], 4),
                                "limb_error_cm": round(measured[2], 3)})
        if body.name == "canonical":
            out = r
    out["bodies"] = entries
    return out


def main(args):
    try:
        if getattr(args, "bodies", None):
            from motion.bodies import load_bodies
            result = evaluate_bodies(args, load_bodies(args.bodies))
        else:
            result = evaluate(args.data, pipeline_options(args), split=args.split, people=args.people,
                              models=args.models, trackers=parse_set(args.trackers), faults=args.faults,
                              max_frames=args.max_frames, max_clips=args.max_clips, dump=args.dump)
    except (FileNotFoundError, ValueError) as e:
        print(f"edge eval: {e}", file=sys.stderr)
        return 2
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(result, indent=2) + "\n")
    keys = ("clips", "frames", "mpjpe_cm", "mpjve_cm_s", "mpjae_cm_s2", "jitter_m_s3", "ee_error_cm",
            "foot_skate_cm_s", "implausible_rate", "penetration_rate", "leg_intersect_rate", "float_rate")
    print("  ".join(f"{k}={result[k]:.4g}" if isinstance(result[k], float) else f"{k}={result[k]}" for k in keys))
    for who, r in result.get("people", {}).items():      # choose on unseen people: they are the users
        print(f"  {who} people: clips={r['clips']}  frames={r['frames']}  mpjpe_cm={r['mpjpe_cm']:.4g}  "
              f"knees_cm={r['knees_cm']:.4g}  ankles_cm={r['ankles_cm']:.4g}  foot_skate_cm_s={r['foot_skate_cm_s']:.4g}")
    for b in result.get("bodies", []):
        print(f"  body {b['name']:<22} {b['height_m']:.2f} m  mpjpe {b['mpjpe_cm']:.2f} cm = {b['mpjpe_pct_height']:.2f} % "
              f"of height  knees {b['knees_cm']:.2f}  ankles {b['ankles_cm']:.2f}  wrists {b['wrists_cm']:.2f} cm  "
              f"under the floor {100 * b['penetration_rate']:.2f} %"
              + (f"  limbs measured within {b['limb_error_cm']:.1f} cm" if "limb_error_cm" in b else ""))
    print(f"wrote {args.json}")
    return 0
