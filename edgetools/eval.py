"""`edge eval`: reconstruction quality on BVH clips or sample files, through the real per-frame pipeline."""
import json
from dataclasses import dataclass
import sys
import time
from pathlib import Path

import numpy as np

from edgetools.bvh import BvhError
from edge.contacts import contact_labels
from edge.imus import ImuNoise, dragposer_drops, mask
from edge.inference import DEFAULT_PRECISION
from edge.features import head_joint, wrist_joints
from edge.pipeline import Pipeline
from edge.plausibility import PlausibilityScorer
from edge.progress import Progress
from edgetools.synth import wear
from edge.skeleton import FEET, JOINT_NAMES, PARENTS
from edgetools.takes import find_clips, load_take
from edgetools import metrics

WARMUP_S = 1.0


@dataclass
class TakeRun:
    """What the pipeline produced for one take, frame-aligned with the input."""
    pred: np.ndarray        # [T,J,3] world joint positions
    pelvis: np.ndarray      # [T,3,3] pelvis rotations
    contacts: np.ndarray    # [T,2] foot-contact probabilities of the output
    sample: np.ndarray      # [T] the sample shown (the target sample during a transition)
    transition: np.ndarray  # [T] frame was part of a sample transition
    cost: np.ndarray        # [T,N] every sample's selection cost when the frame was judged (N>1)
    samples: np.ndarray = None  # [T,N,J,3] every sample's pose of the frame (N>1, with keep_samples)


def run_take(pipe, take, max_frames=None, keep_samples=False, signals=None):
    """Feed a take (or these signals of it) frame by frame through the pipeline. Output frame o arrives
    tau frames after input o."""
    signals = take.signals if signals is None else signals
    T = take.frames if max_frames is None else min(take.frames, max_frames)
    N = pipe.samples
    run = TakeRun(np.zeros((T, len(JOINT_NAMES), 3)), np.zeros((T, 3, 3)), np.zeros((T, 2)),
                  np.zeros(T, np.int16), np.zeros(T, bool), np.zeros((T, N), np.float32),
                  np.zeros((T, N, len(JOINT_NAMES), 3), np.float32) if keep_samples and N > 1 else None)

    def keep(pose):
        f = pose.frame
        run.pred[f], run.pelvis[f], run.contacts[f] = pose.positions, pose.rotations[0], pose.contacts
        run.sample[f], run.transition[f] = pose.sample, pose.transition

    pipe.reset()
    for t in range(T):
        pose = pipe.step(signals.slice(t, t + 1))
        run.cost[t] = pipe.buffer.cost[pipe.buffer.slot(t)]
        if run.samples is not None:         # frame t's poses of every sample, after IK
            run.samples[t] = pipe._pos[:N]
        if pose is not None:
            keep(pose)
    for pose in pipe.flush():
        keep(pose)
    return run


def take_signals(take, trackers, faults=None, seed=0, index=0, imu_noise=None):
    """The take's signals as the board would see them with the extra IMUs `trackers` worn: IMU noise
    (`imu_noise`, by default edge.imus.ImuNoise as training synthesises it) and, with faults='disconnect', DragPoser's
    faulty-sensor protocol on them (each frame one tracker drops with probability 1 % for 100 frames),
    through the synchroniser's hold and fade. Seeded per take."""
    if not trackers:
        return take.signals
    rng = np.random.default_rng([seed, index, 13])
    worn = mask(trackers)
    alive = dragposer_drops(rng, take.frames, worn, take.fps) if faults == "disconnect" else None
    return wear(take.signals, worn, take.fps, rng, ImuNoise() if imu_noise is None else imu_noise, alive)


def evaluate(paths, split=None, samples=1, no_ssi=False, precision=DEFAULT_PRECISION, max_frames=None, dump=None,
             models=None, seed=0, lookahead=None, ik=True, log=print, trackers=(), faults=None, segments=True,
             selection=None, max_clips=None, imu_noise=None, refine=None, heading=True):
    files = find_clips(paths, split)
    if max_clips and len(files) > max_clips:        # an even spread over the list (a quick subset)
        files = [files[i] for i in np.linspace(0, len(files) - 1, max_clips).round().astype(int)]
    if not files:
        raise SystemExit(f"edge eval: no clips found in {paths}" + (f" for split {split!r}" if split else ""))
    if faults not in (None, "disconnect"):
        raise ValueError(f"--faults {faults!r}: edge eval knows 'disconnect' (DragPoser's protocol on the extra trackers)")
    pipe = Pipeline(models, samples=samples, seed=seed, precision=precision, ssi=not no_ssi, lookahead=lookahead,
                    foot_ik=ik, arm_ik=ik, segments=segments, selection=selection, refine=refine,
                    heading=heading)
    if trackers and not pipe.imus:
        raise ValueError(f"--trackers {','.join(trackers)}: the model in {models or 'models/'} reads no extra IMUs "
                         f"(its decoder takes {pipe.n_features} features)")
    phys, phys_gt, div = [], [], []
    scorer = PlausibilityScorer(pipe.autoencoder, pipe.threshold)
    parts, per_clip, skipped = [], [], []
    switches = switch_frames = 0
    peaks_after, peaks_quiet, gt_after, gt_quiet = [], [], [], []
    if dump:
        Path(dump).mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    with Progress(len(files), "eval") as bar:
        for index, f in enumerate(files):
            try:
                take = load_take(f)
            except BvhError as e:
                skipped.append(str(e))
                log(f"skipped: {e}")
                bar.update()
                continue
            run = run_take(pipe, take, max_frames, keep_samples=samples > 1,
                           signals=take_signals(take, trackers, faults, seed, index, imu_noise))
            pred, pelvis = run.pred, run.pelvis
            switches += pipe.switch_count
            switch_frames += int(run.transition.sum())
            T = len(pred)
            w = int(round(WARMUP_S * take.fps))
            if T - w < 4:
                skipped.append(f"{f}: shorter than the {WARMUP_S:.0f} s warm-up")
                bar.update()
                continue
            sig = take.signals.slice(0, T)
            head = head_joint(sig.head_pos, sig.head_rot)
            wrists = wrist_joints(sig.hand_pos, sig.hand_rot)
            bad = scorer.lower_body_error(pred[w:], pelvis[w:]) > scorer.threshold
            starts = [s0 - w for _, s0, _, _ in pipe.switches]
            after, quiet = metrics.transition_peaks(pred[w:], take.fps, starts)
            peaks_after += after
            peaks_quiet += quiet
            # The same windows on the ground truth: how much of the ratio the motion itself brings.
            after, quiet = metrics.transition_peaks(take.gt_pos[w:T], take.fps, starts)
            gt_after += after
            gt_quiet += quiet
            m = metrics.clip_metrics(pred[w:], take.gt_pos[w:T], take.fps, head[w:], wrists[w:], bad)
            parts.append(m)
            phys.append(metrics.physical_metrics(pred[w:], run.contacts[w:]))
            phys_gt.append(metrics.physical_metrics(take.gt_pos[w:T], contact_labels(take.gt_pos[:T, FEET], take.fps)[w:]))
            if run.samples is not None:
                div.append(metrics.diversity_metrics(run.samples[w:], take.gt_pos[w:T]))
            s = metrics.summarize([m])
            per_clip.append({"clip": str(f), "frames": s["frames"], "mpjpe_cm": round(s["mpjpe_cm"], 3),
                             "implausible_rate": round(s["implausible_rate"], 4)})
            if dump:
                np.savez_compressed(Path(dump) / (Path(f).stem + ".npz"), joint_names=np.array(JOINT_NAMES),
                                    parents=PARENTS, fps=take.fps, gt_pos=take.gt_pos[:T].astype(np.float32),
                                    pred_pos=pred.astype(np.float32), contacts=run.contacts.astype(np.float32),
                                    sample=run.sample, transition=run.transition, cost=run.cost,
                                    implausible=np.concatenate([np.zeros(w, bool), bad]),
                                    switches=np.array([s[:2] for s in pipe.switches], np.int64).reshape(-1, 2),
                                    threshold=pipe.threshold, warmup_frames=w)
            bar.update(postfix=f"mpjpe {metrics.summarize(parts)['mpjpe_cm']:.2f} cm")
    if not parts:
        raise SystemExit("edge eval: no clip could be evaluated: " + "; ".join(skipped))
    result = {"clips": len(parts), "samples": samples, "ssi": pipe.ssi, "precision": precision,
              "precision_in_use": pipe.precision, "precision_note": pipe.precision_note, "ik": ik,
              "trackers": ["waist", *trackers], "faults": faults, "decoder_features": pipe.n_features,
              "imu_segments": pipe.segments, "heading_observer": pipe.heading is not None, "selection": [(c.name, c.weight) for c in pipe.criteria.criteria],
              "lookahead_frames": pipe.lookahead, "ssi_switches": switches, "transition_frames": switch_frames,
              "split": split, "warmup_s": WARMUP_S, **metrics.summarize(parts),
              **metrics.summarize_physical(phys), "ground_truth": metrics.summarize_physical(phys_gt),
              "diversity": metrics.summarize_diversity(div),
              "transition_jerk": {
                  "switches_measured": len(peaks_after),
                  "peak_after_switch_mean_m_s3": float(np.mean(peaks_after)) if peaks_after else None,
                  "peak_quiet_window_median_m_s3": float(np.median(peaks_quiet)) if peaks_quiet else None,
                  "ratio": float(np.mean(peaks_after) / np.median(peaks_quiet)) if peaks_after and peaks_quiet else None,
                  "ground_truth_same_windows": {
                      "peak_after_switch_mean_m_s3": float(np.mean(gt_after)) if gt_after else None,
                      "peak_quiet_window_median_m_s3": float(np.median(gt_quiet)) if gt_quiet else None,
                      "ratio": float(np.mean(gt_after) / np.median(gt_quiet)) if gt_after and gt_quiet else None}},
              "plausibility_threshold_m": pipe.threshold, "seconds": round(time.time() - t0, 1),
              "joint_names": list(JOINT_NAMES), "skipped": skipped, "per_clip": per_clip}
    return result


def refine_settings(args):
    """--refine [--refine-steps K] [--refine-terms a,b]: the Pipeline's refine= (None: off)."""
    if not getattr(args, "refine", False):
        return None
    out = {"steps": args.refine_steps}
    if args.refine_terms:
        out["terms"] = [t.strip() for t in args.refine_terms.split(",") if t.strip()]
    return out


def main(args):
    try:
        from edge.imus import parse_set
        result = evaluate(args.data, args.split, args.samples, args.no_ssi, args.precision, args.max_frames,
                          args.dump, args.models, args.seed, args.lookahead, not args.no_ik,
                          trackers=parse_set(args.trackers), faults=args.faults, segments=not args.no_segments,
                          refine=refine_settings(args), heading=not getattr(args, "no_heading", False))
    except (FileNotFoundError, ValueError) as e:
        print(f"edge eval: {e}", file=sys.stderr)
        return 2
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(result, indent=2) + "\n")
    keys = ("clips", "frames", "mpjpe_cm", "mpjve_cm_s", "mpjae_cm_s2", "jitter_m_s3", "ee_error_cm",
            "foot_skate_cm_s", "implausible_rate", "penetration_rate", "leg_intersect_rate", "float_rate")
    print("  ".join(f"{k}={result[k]:.4g}" if isinstance(result[k], float) else f"{k}={result[k]}" for k in keys))
    print(f"wrote {args.json}")
    return 0
