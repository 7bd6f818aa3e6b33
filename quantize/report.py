"""fp32 against int8, measured in one run:

    python -m quantize.report --data ../shared/mocap --json out/quant_report.json [--samples 32]
                              [--drift-frames 3000] [--timing-frames 600] [--max-clips K]

- accuracy on the `val` split through the real pipeline (motion.evaluate.evaluate, N=32): mpjpe, implausible rate;
- selection agreement: per val take, motion.evaluate.run_take with both precisions; how often SSI shows the same sample;
- closed-loop drift: both decoders on the same feature stream (the bundled sample's, looped to 3,000
  frames), each fed its own GRU state; rot6d and FK joint-position differences at frames 100/1000/3000;
- model file sizes;
- latency on one pinned core, fp32 and int8 interleaved in the same run: the bare decoder call at N=32
  and N=100 and the whole pipeline step at N=100.

Targets (from the int8 issue): mpjpe within +2 % of fp32 at N=32, implausible rate within +10 % relative,
int8 decoder file <= 40 % of fp32, int8 pipeline at N=100 >= 1.5x faster than fp32.
"""
import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from edge import quat
from motion.evaluate import evaluate, run_take
from edge.features import sequence_features
from edge.inference import make_session
from edge.modelfiles import DEFAULT_DIR, ModelError, load_manifest
from edge.options import PipelineOptions
from edge.pipeline import Pipeline
from edge.progress import Progress
from motion.takes import find_clips, from_sample, load_take
from motion.timing import time_calls
from quantize.common import MODELS, fp32_name, head_anchored_positions, int8_name, latents_for, pin_one_core, rollout

ROOT = Path(__file__).resolve().parent.parent
SAMPLE = ROOT / "samples" / "cmu_09_12_walk.npz"
PRECISIONS = ("fp32", "int8")
TARGETS = {"mpjpe_rel_max": 1.02, "implausible_rel_max": 1.10, "decoder_size_max": 0.40, "pipeline_speedup_min": 1.5}


def accuracy(data, samples, max_clips, models, log):
    out = {}
    for prec in PRECISIONS:
        paths = find_clips([data], "val")[:max_clips] if max_clips else [data]
        r = evaluate(paths, PipelineOptions(samples=samples, precision=prec), split=None if max_clips else "val",
                     models=models, log=log)
        out[prec] = {k: r[k] for k in ("clips", "frames", "mpjpe_cm", "implausible_rate", "ssi_switches",
                                       "jitter_m_s3", "foot_skate_cm_s", "seconds")}
    return out


def selection_agreement(data, samples, max_clips, models):
    """Fraction of frames where both precisions show the same sample (run_take on every val take)."""
    files = find_clips([data], "val")[:max_clips or None]
    pipes = {p: Pipeline(PipelineOptions(samples=samples, precision=p), models=models) for p in PRECISIONS}
    same = frames = 0
    per_take_min = 1.0
    switches = {p: 0 for p in PRECISIONS}
    first_diff, pose_diff = [], []
    with Progress(len(files), "selection") as bar:
        for f in files:
            try:
                take = load_take(f)
            except Exception:  # unreadable clips are skipped the same way by evaluate
                bar.update()
                continue
            runs = {p: run_take(pipes[p], take) for p in PRECISIONS}
            for p in PRECISIONS:
                switches[p] += len(pipes[p].switches)
            eq = runs["fp32"].sample == runs["int8"].sample
            first_diff.append(int(np.argmin(eq)) if not eq.all() else len(eq))
            pose_diff.append(np.linalg.norm(runs["fp32"].pred - runs["int8"].pred, axis=-1).mean(axis=1))
            same += int(eq.sum())
            frames += len(eq)
            per_take_min = min(per_take_min, float(eq.mean()))
            bar.update(postfix=f"agree {same / max(frames, 1):.3f}")
    pd = np.concatenate(pose_diff) * 100 if pose_diff else np.zeros(1)
    return {"frames": frames, "agreement": same / max(frames, 1), "worst_take_agreement": per_take_min,
            "switches": switches, "takes": len(first_diff),
            "takes_never_disagreeing": int(sum(f == len(d) for f, d in zip(first_diff, pose_diff, strict=True))),
            "first_disagreement_frame_median": float(np.median(first_diff)) if first_diff else None,
            "output_pose_diff_cm": {"mean": float(pd.mean()), "p95": float(np.percentile(pd, 95)),
                                    "note": "mean joint distance between the fp32 and int8 outputs, per frame"}}


def drift(models, frames=3000, rows=32, checkpoints=(100, 1000, 3000)):
    """Both decoders, closed loop, on the bundled sample's features looped to `frames` frames."""
    take = from_sample(SAMPLE)
    folder = Path(models) if models else DEFAULT_DIR
    feats, _, yaw_q = sequence_features(take.signals, take.fps,
                                        n_features=json.loads((folder / "manifest.json").read_text())["features"])
    root = quat.to_matrix(quat.mul(quat.inv(yaw_q), take.signals.waist_rot))     # puck in the character frame
    reps = -(-frames // len(feats))
    feats = np.tile(feats, (reps, 1))[:frames].astype(np.float32)
    root = np.tile(root, (reps, 1, 1))[:frames]
    F = np.repeat(feats[:, None], rows, axis=1)
    z = latents_for(rows, seed=3)
    folder = Path(models) if models else DEFAULT_DIR
    r6 = {p: rollout(make_session(folder / (fp32_name("decoder") if p == "fp32" else int8_name("decoder"))), F, z)[0]
          for p in PRECISIONS}
    R = np.repeat(root[:, None], rows, axis=1)
    pos = {p: head_anchored_positions(r6[p], R) for p in PRECISIONS}
    d6 = np.abs(r6["int8"] - r6["fp32"])                          # [T,B,120]
    dp = np.linalg.norm(pos["int8"] - pos["fp32"], axis=-1)       # [T,B,J] metres
    out = {"frames": frames, "rows": rows, "latents": "row 0 at the prior mean, the others N(0,1)",
           "stream": f"{SAMPLE.name} features looped ({len(take.signals.head_pos)} frames per loop)", "at": {}}
    for c in checkpoints:
        if c > frames:
            continue
        t = c - 1
        out["at"][str(c)] = {
            "rot6d_abs_max": float(d6[t].max()), "rot6d_abs_mean": float(d6[t].mean()),
            "pos_cm_max": float(dp[t].max() * 100), "pos_cm_mean": float(dp[t].mean() * 100),
            "pos_cm_max_so_far": float(dp[:c].max() * 100), "pos_cm_mean_so_far": float(dp[:c].mean() * 100),
            "prior_mean_row_pos_cm_max": float(dp[t, 0].max() * 100)}
    # Does the difference grow with time? Mean over the last loop vs the first.
    L = len(take.signals.head_pos)
    out["pos_cm_mean_first_loop"] = float(dp[:L].mean() * 100)
    out["pos_cm_mean_last_loop"] = float(dp[-L:].mean() * 100)
    return out


def sizes(models):
    m = load_manifest(Path(models) if models else DEFAULT_DIR,
                      need=tuple(n(k) for k in MODELS for n in (fp32_name, int8_name)))
    out = {}
    for k in MODELS:
        a, b = Path(m["paths"][fp32_name(k)]).stat().st_size, Path(m["paths"][int8_name(k)]).stat().st_size
        out[k] = {"fp32_bytes": a, "int8_bytes": b, "ratio": b / a}
    return out


def latency(models, frames=600, rounds=6):
    """Microseconds on one pinned core; fp32 and int8 alternate in `rounds` blocks so drift in the
    machine's speed hits both alike."""
    core = pin_one_core()
    take = from_sample(SAMPLE)
    sig = [take.signals.slice(t, t + 1) for t in range(take.frames)]
    res = {"core": core, "frames_per_precision": frames}
    for n in (32, 100):
        pipes = {p: Pipeline(PipelineOptions(samples=n, precision=p), models=models) for p in PRECISIONS}
        for p in pipes.values():
            for t in range(120):
                p.step(sig[t % len(sig)])
        whole = {p: [] for p in PRECISIONS}
        bare = {p: [] for p in PRECISIONS}
        k = frames // rounds
        for r in range(rounds):
            for p in (PRECISIONS if r % 2 == 0 else PRECISIONS[::-1]):
                pipe = pipes[p]
                if n == 100:
                    whole[p].append(time_calls(lambda i, pipe=pipe, r=r, k=k: pipe.step(sig[(120 + r * k + i) % len(sig)]), k))
                bare[p].append(time_calls(lambda i, pipe=pipe: pipe.decoder.step(), k))
        for p in PRECISIONS:
            b = np.concatenate(bare[p])
            res[f"decoder_n{n}_{p}"] = {"p50": float(np.median(b)), "p99": float(np.percentile(b, 99))}
            if whole[p]:
                w = np.concatenate(whole[p])
                res[f"pipeline_n{n}_{p}"] = {"p50": float(np.median(w)), "p99": float(np.percentile(w, 99))}
        res[f"decoder_n{n}_speedup"] = res[f"decoder_n{n}_fp32"]["p50"] / res[f"decoder_n{n}_int8"]["p50"]
    res["pipeline_n100_speedup"] = res["pipeline_n100_fp32"]["p50"] / res["pipeline_n100_int8"]["p50"]
    res["decoder_share_of_pipeline_n100_fp32"] = res["decoder_n100_fp32"]["p50"] / res["pipeline_n100_fp32"]["p50"]
    return res


def verdict(r):
    acc, sz, lat = r.get("accuracy"), r["sizes"], r["latency"]
    checks = {}
    if acc:
        f, i = acc["fp32"], acc["int8"]
        checks["mpjpe_within_2pct"] = {"value": i["mpjpe_cm"] / f["mpjpe_cm"], "target": f"<= {TARGETS['mpjpe_rel_max']}",
                                       "met": i["mpjpe_cm"] <= TARGETS["mpjpe_rel_max"] * f["mpjpe_cm"]}
        ratio = i["implausible_rate"] / f["implausible_rate"] if f["implausible_rate"] > 0 else (
            1.0 if i["implausible_rate"] == 0 else float("inf"))
        checks["implausible_within_10pct"] = {"value": ratio, "target": f"<= {TARGETS['implausible_rel_max']}",
                                              "met": ratio <= TARGETS["implausible_rel_max"]}
    checks["decoder_size_le_40pct"] = {"value": sz["decoder"]["ratio"], "target": f"<= {TARGETS['decoder_size_max']}",
                                       "met": sz["decoder"]["ratio"] <= TARGETS["decoder_size_max"]}
    checks["pipeline_n100_speedup_ge_1_5"] = {"value": lat["pipeline_n100_speedup"],
                                              "target": f">= {TARGETS['pipeline_speedup_min']}",
                                              "met": lat["pipeline_n100_speedup"] >= TARGETS["pipeline_speedup_min"],
                                              "bare_decoder_n100_speedup": lat["decoder_n100_speedup"]}
    return checks


def table(r):
    lines = []
    add = lines.append
    add(f"{'':34s} {'fp32':>10s} {'int8':>10s} {'int8/fp32':>10s}")
    acc = r.get("accuracy")
    if acc:
        f, i = acc["fp32"], acc["int8"]
        n = r["samples"]
        add(f"{f'val mpjpe_cm (N={n})':34s} {f['mpjpe_cm']:10.3f} {i['mpjpe_cm']:10.3f} {i['mpjpe_cm'] / f['mpjpe_cm']:10.4f}")
        fr, ir = f["implausible_rate"], i["implausible_rate"]
        add(f"{f'val implausible_rate (N={n})':34s} {fr:10.5f} {ir:10.5f} {ir / fr if fr else float('nan'):10.4f}")
        add(f"{'val ssi_switches':34s} {f['ssi_switches']:10d} {i['ssi_switches']:10d}")
    sel = r.get("selection")
    if sel:
        add(f"{'selection agreement (frames)':34s} {sel['agreement']:10.4f}   worst take {sel['worst_take_agreement']:.4f}, "
            f"{sel['takes_never_disagreeing']}/{sel['takes']} takes never differ, first difference at frame "
            f"{sel['first_disagreement_frame_median']:.0f} (median)")
        add(f"{'output pose fp32 vs int8 cm':34s} {sel['output_pose_diff_cm']['mean']:10.3f}   p95 "
            f"{sel['output_pose_diff_cm']['p95']:.3f} (mean joint distance between the two outputs)")
    d = r.get("drift")
    if d:
        for c, v in d["at"].items():
            add(f"{f'drift @ frame {c}: rot6d max/mean':34s} {v['rot6d_abs_max']:10.4f} {v['rot6d_abs_mean']:10.5f}")
            add(f"{f'drift @ frame {c}: FK pos cm max/mean':34s} {v['pos_cm_max']:10.3f} {v['pos_cm_mean']:10.4f}"
                f"   (max so far {v['pos_cm_max_so_far']:.2f})")
    for k, v in r["sizes"].items():
        add(f"{k + ' file bytes':34s} {v['fp32_bytes']:10,d} {v['int8_bytes']:10,d} {v['ratio']:10.3f}")
    lat = r["latency"]
    for key, label in (("decoder_n32", "decoder call N=32 us p50"), ("decoder_n100", "decoder call N=100 us p50"),
                       ("pipeline_n100", "pipeline step N=100 us p50")):
        a, b = lat[f"{key}_fp32"]["p50"], lat[f"{key}_int8"]["p50"]
        add(f"{label:34s} {a:10.1f} {b:10.1f} {b / a:10.3f}   speedup {a / b:.2f}x")
    add("")
    for k, v in r["targets"].items():
        extra = f" (bare decoder {v['bare_decoder_n100_speedup']:.2f}x)" if "bare_decoder_n100_speedup" in v else ""
        add(f"target {k:32s} {v['value']:.4g} {v['target']:>8s}  {'MET' if v['met'] else 'NOT MET'}{extra}")
    return "\n".join(lines)


def main(argv=None):
    ap = argparse.ArgumentParser(prog="python -m quantize.report", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", help="mocap folder (val split); without it only drift, sizes and latency are measured")
    ap.add_argument("--json", default="out/quant_report.json")
    ap.add_argument("--models", help="model folder (default: the shipped models/)")
    ap.add_argument("--samples", type=int, default=32)
    ap.add_argument("--max-clips", type=int, default=None, help="only the first K val clips (quick look)")
    ap.add_argument("--drift-frames", type=int, default=3000)
    ap.add_argument("--timing-frames", type=int, default=600)
    a = ap.parse_args(argv)
    t0 = time.time()
    quiet = []
    try:
        r = {"samples": a.samples, "sizes": sizes(a.models)}
        if a.data:
            r["accuracy"] = accuracy(a.data, a.samples, a.max_clips, a.models, quiet.append)
            r["selection"] = selection_agreement(a.data, a.samples, a.max_clips, a.models)
        r["drift"] = drift(a.models, a.drift_frames)
        r["latency"] = latency(a.models, a.timing_frames)
    except ModelError as e:
        print(f"quantize.report: {e}", file=sys.stderr)
        return 2
    r["targets"] = verdict(r)
    r["seconds"] = round(time.time() - t0, 1)
    if quiet:
        r["skipped"] = quiet
    Path(a.json).parent.mkdir(parents=True, exist_ok=True)
    Path(a.json).write_text(json.dumps(r, indent=2) + "\n")
    print(table(r))
    print(f"wrote {a.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
