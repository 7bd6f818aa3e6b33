"""Reconstruction quality on BVH clips or sample files, through the real per-frame pipeline: the library
behind `edge eval` (edgetools.eval), the benchmarks and the int8 report."""
from dataclasses import dataclass, replace
import time
from pathlib import Path

import numpy as np

from motion.bvh import BvhError
from motion.contacts import contact_labels
from edge.calibration import devices_on_canonical, height_scale_for
from edge.imus import ImuNoise, dragposer_drops, mask
from edge.features import head_joint, wrist_joints
from edge.options import PipelineOptions
from edge.pipeline import Pipeline
from edge.plausibility import PlausibilityScorer
from edge.progress import Progress
from edge.proportions import UserBody
from motion.synth import bend_hands, wear
from edge.skeleton import FEET, JOINT_NAMES, PARENTS
from motion.takes import PEOPLE, find_clips, load_take, people_of_files
from motion import metrics

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


def run_take(pipe, take, max_frames=None, keep_samples=False, signals=None, user_body=None):
    """Feed a take (or these signals of it) frame by frame through the pipeline. Output frame o arrives
    tau frames after input o. user_body (edge.proportions.UserBody): the poses put on the user's legs,
    as the board sends them when told the user's leg length."""
    signals = take.signals if signals is None else signals
    T = take.frames if max_frames is None else min(take.frames, max_frames)
    N = pipe.samples
    run = TakeRun(np.zeros((T, len(JOINT_NAMES), 3)), np.zeros((T, 3, 3)), np.zeros((T, 2)),
                  np.zeros(T, np.int16), np.zeros(T, bool), np.zeros((T, N), np.float32),
                  np.zeros((T, N, len(JOINT_NAMES), 3), np.float32) if keep_samples and N > 1 else None)

    def keep(pose):
        if user_body is not None:
            pose = user_body.on_user(pose)
        f = pose.frame
        run.pred[f], run.pelvis[f], run.contacts[f] = pose.positions, pose.rotations[0], pose.contacts
        run.sample[f], run.transition[f] = pose.sample, pose.transition

    pipe.reset()
    for t in range(T):
        pose = pipe.step(signals.slice(t, t + 1))
        run.cost[t] = pipe.buffer.cost[pipe.buffer.slot(t)]
        if run.samples is not None:         # frame t's poses of every sample, after IK
            run.samples[t] = pipe.bufs.pos[:N]
        if pose is not None:
            keep(pose)
    for pose in pipe.flush():
        keep(pose)
    return run


def take_signals(take, trackers, faults=None, seed=0, index=0, imu_noise=None, hand_bend=None):
    """The take's signals as the board would see them with the extra IMUs `trackers` worn: IMU noise
    (`imu_noise`, by default edge.imus.ImuNoise as training synthesises it) and, with faults='disconnect', DragPoser's
    faulty-sensor protocol on them (each frame one tracker drops with probability 1 % for 100 frames),
    through the synchroniser's hold and fade; with hand_bend (flexion, deviation std in degrees) the
    hands bent at the wrist (motion.synth.bend_hands). Seeded per take."""
    sig = take.signals
    if hand_bend:
        sig = bend_hands(sig, take.fps, np.random.default_rng([seed, index, 17]), *hand_bend)
    if not trackers:
        return sig
    rng = np.random.default_rng([seed, index, 13])
    worn = mask(trackers)
    alive = dragposer_drops(rng, take.frames, worn, take.fps) if faults == "disconnect" else None
    return wear(sig, worn, take.fps, rng, ImuNoise() if imu_noise is None else imu_noise, alive)


def evaluate(paths, options=None, *, split=None, people=None, models=None, trackers=(), faults=None, imu_noise=None,
             hand_bend=None, max_frames=None, max_clips=None, dump=None, log=print, conventions=True, body=None,
             body_known=False, limbs=None):
    """Every clip of `paths` (BVH files, folders, sample .npz; a folder filtered by its MANIFEST.tsv's
    `split`, and with `people` to the performers the model never saw or those it saw) through a
    Pipeline(options, models), wearing the extra IMUs `trackers` (with `faults`: DragPoser's disconnect
    protocol; `imu_noise`: edge.imus.ImuNoise by default), scored after a WARMUP_S warm-up. Returns the
    JSON `edge eval` writes, with the same metrics for unseen and seen people apart under "people";
    `dump` also writes one .npz per clip. conventions=False scores BVH clips against their retargeting
    with the sources' skeleton conventions left in (the ruler before motion.neutrals). body
    (motion.bodies.Body): each BVH clip posed on that body, its devices synthesised from it and brought
    onto the canonical body as the standing calibration does, the poses taken back to the body's size
    and scored against its FK; body_known: the runtime is told the body's limbs (a [body] leg_length_m
    in the board's config, the arms the T-pose measures) and sends its poses on them
    (edge.proportions.UserBody); limbs (legs, arms): the runtime is told these instead (what the board
    measured of the body, motion.bodies.measured_limbs)."""
    options = PipelineOptions() if options is None else options
    user_body = (UserBody(*limbs) if limbs is not None and body is not None
                 else UserBody(body.legs, body.arms) if body_known and body is not None else None)
    files = _clips(paths, split, max_clips, people)
    who = people_of_files(paths, files)
    if faults not in (None, "disconnect"):
        raise ValueError(f"--faults {faults!r}: edge eval knows 'disconnect' (DragPoser's protocol on the extra trackers)")
    pipe = Pipeline(options, models=models)
    if trackers and not pipe.imus:
        raise ValueError(f"--trackers {','.join(trackers)}: the model in {models or 'models/'} reads no extra IMUs "
                         f"(its decoder takes {pipe.n_features} features)")
    tally = Tally(PlausibilityScorer(pipe.autoencoder, pipe.threshold))
    if dump:
        Path(dump).mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    with Progress(len(files), "eval") as bar:
        for index, f in enumerate(files):
            try:
                take = (load_take(f) if conventions else load_take(f, conventions=False)) if body is None \
                    else body_take(f, body)
            except BvhError as e:
                tally.skipped.append(str(e))
                log(f"skipped: {e}")
                bar.update()
                continue
            fed = take_signals(take, trackers, faults, options.seed, index, imu_noise, hand_bend)
            scale = 1.0 if body is None else on_canonical_scale(body)
            if scale != 1.0:
                fed = replace(fed, **dict(zip(("head_pos", "hand_pos"), devices_on_canonical(
                    fed.head_pos, fed.head_rot, fed.hand_pos, fed.hand_rot, scale), strict=True)))
            run = run_take(pipe, take, max_frames, keep_samples=pipe.samples > 1, signals=fed, user_body=user_body)
            if scale != 1.0:                        # the poses back in the user's size, as the outputs send them
                run.pred /= scale
                if run.samples is not None:
                    run.samples /= scale
            tally.add(f, take, run, pipe, dump, who.get(f), fed.hand_rot)
            bar.update(postfix=f"mpjpe {metrics.summarize(tally.parts)['mpjpe_cm']:.2f} cm" if tally.parts else None)
    if not tally.parts:
        raise SystemExit("edge eval: no clip could be evaluated: " + "; ".join(tally.skipped))
    return {**_run_settings(pipe, options, split, people, trackers, faults), **tally.summary(),
            "seconds": round(time.time() - t0, 1), "joint_names": list(JOINT_NAMES)}


def body_take(path, body):
    """A BVH clip on `body` (motion.bodies.take_on)."""
    from motion.bodies import take_on
    from motion.retarget import load_motion
    from motion.takes import FPS
    if not str(path).lower().endswith(".bvh"):
        raise BvhError(f"{path}: a body other than the canonical one needs a BVH clip (its rotations), not a sample")
    return take_on(load_motion(path, FPS), body, FPS, str(path))


def on_canonical_scale(body):
    """The height scale the standing calibration measures on `body` (its headset's height standing)."""
    from motion.bodies import eye_height
    return height_scale_for(eye_height(body.offsets()))


def _clips(paths, split, max_clips, people=None):
    files = find_clips(paths, split, people)
    if max_clips and len(files) > max_clips:        # an even spread over the list (a quick subset)
        files = [files[i] for i in np.linspace(0, len(files) - 1, max_clips).round().astype(int)]
    if not files:
        raise SystemExit(f"edge eval: no clips found in {paths}" + (f" for split {split!r}" if split else "")
                         + (f" of {people} people" if people else ""))
    return files


def _run_settings(pipe, options, split, people, trackers, faults):
    """What ran: the part of the result that says how, before what it measured."""
    return {"samples": options.samples, "ssi": pipe.ssi, "precision": options.precision,
            "precision_in_use": pipe.precision, "precision_note": pipe.precision_note,
            "ik": options.foot_ik and options.arm_ik, "trackers": ["waist", *trackers], "faults": faults,
            "decoder_features": pipe.n_features, "imu_segments": pipe.segments,
            "heading_observer": pipe.heading is not None,
            "selection": [(c.name, c.weight) for c in pipe.criteria.criteria], "lookahead_frames": pipe.lookahead,
            "split": split, "people_filter": people, "warmup_s": WARMUP_S, "plausibility_threshold_m": pipe.threshold}


class Tally:
    """The metrics of the clips evaluated so far: per clip (with whose clip it is: unseen or seen
    people), then summed up by summary() over all of them and over each group."""

    def __init__(self, scorer):
        self.scorer = scorer
        self.clips, self.per_clip, self.skipped = [], [], []

    @property
    def parts(self):
        return [c["part"] for c in self.clips]

    def add(self, f, take, run, pipe, dump, people=None, hand_rot=None):
        """One clip's run (a TakeRun of `pipe` on `take`, file `f`, fed the controllers' hand_rot), after its warm-up."""
        pred, pelvis = run.pred, run.pelvis
        T, w = len(pred), int(round(WARMUP_S * take.fps))
        if T - w < 4:
            self.skipped.append(f"{f}: shorter than the {WARMUP_S:.0f} s warm-up")
            return
        sig, gt = take.signals.slice(0, T), take.gt_pos[:T]
        head, wrists = head_joint(sig.head_pos, sig.head_rot), wrist_joints(sig.hand_pos, sig.hand_rot)
        bad = self.scorer.lower_body_error(pred[w:], pelvis[w:]) > self.scorer.threshold
        starts = [s0 - w for _, s0, _, _ in pipe.switches]
        clip = {"people": people, "switches": pipe.switch_count, "switch_frames": int(run.transition.sum()),
                "peaks": {}}
        # The jerk around switches, and in the same windows of the ground truth: how much the motion brings.
        for key, pos in (("", pred[w:]), ("gt_", gt[w:])):
            clip["peaks"][key + "after"], clip["peaks"][key + "quiet"] = metrics.transition_peaks(pos, take.fps, starts)
        clip["part"] = m = metrics.clip_metrics(pred[w:], gt[w:], take.fps, head[w:], wrists[w:], bad)
        clip["phys"] = phys = metrics.physical_metrics(pred[w:], run.contacts[w:])
        clip["phys_gt"] = metrics.physical_metrics(gt[w:], contact_labels(gt[:, FEET], take.fps)[w:])
        clip["div"] = metrics.diversity_metrics(run.samples[w:], gt[w:]) if run.samples is not None else None
        self.clips.append(clip)
        s = metrics.summarize([m])
        self.per_clip.append({"clip": str(f), "people": people, "frames": s["frames"],
                              "mpjpe_cm": round(s["mpjpe_cm"], 3),
                              "implausible_rate": round(s["implausible_rate"], 4),
                              "leg_intersect_frames": phys["intersect_n"], "float_frames": phys["float_n"]})
        if dump:
            np.savez_compressed(Path(dump) / (Path(f).stem + ".npz"), joint_names=np.array(JOINT_NAMES),
                                parents=PARENTS, fps=take.fps, gt_pos=gt.astype(np.float32),
                                pred_pos=pred.astype(np.float32), contacts=run.contacts.astype(np.float32),
                                hand_rot=(sig.hand_rot if hand_rot is None else hand_rot[:T]).astype(np.float32),
                                sample=run.sample, transition=run.transition, cost=run.cost,
                                implausible=np.concatenate([np.zeros(w, bool), bad]),
                                switches=np.array([s[:2] for s in pipe.switches], np.int64).reshape(-1, 2),
                                threshold=pipe.threshold, warmup_frames=w)

    def summary(self):
        """Every metric over all clips, the per-clip table, and under "people" the same metrics for the
        clips of unseen and of seen people (when a manifest says whose clips they are)."""
        out = {**self._summarize(self.clips), "skipped": self.skipped, "per_clip": self.per_clip}
        groups = {g: [c for c in self.clips if c["people"] == g] for g in PEOPLE}
        if any(groups.values()):
            out["people"] = {g: self._summarize(cs) for g, cs in groups.items() if cs}
        return out

    def _summarize(self, clips):
        if not clips:
            return {"clips": 0}
        return {"clips": len(clips), "ssi_switches": sum(c["switches"] for c in clips),
                "transition_frames": sum(c["switch_frames"] for c in clips),
                **metrics.summarize([c["part"] for c in clips]),
                **metrics.summarize_physical([c["phys"] for c in clips]),
                "ground_truth": metrics.summarize_physical([c["phys_gt"] for c in clips]),
                "diversity": metrics.summarize_diversity([c["div"] for c in clips if c["div"] is not None]),
                "transition_jerk": self._jerk(clips)}

    @staticmethod
    def _jerk(clips):
        """RPM's transition jerk: the peak after each switch against the median quiet window, for the
        prediction and for the ground truth in the same windows."""
        def ratio(after, quiet):
            return float(np.mean(after) / np.median(quiet)) if after and quiet else None

        def mean(x):
            return float(np.mean(x)) if x else None

        def median(x):
            return float(np.median(x)) if x else None

        k = {key: [v for c in clips for v in c["peaks"][key]] for key in ("after", "quiet", "gt_after", "gt_quiet")}
        return {"switches_measured": len(k["after"]),
                "peak_after_switch_mean_m_s3": mean(k["after"]), "peak_quiet_window_median_m_s3": median(k["quiet"]),
                "ratio": ratio(k["after"], k["quiet"]),
                "ground_truth_same_windows": {
                    "peak_after_switch_mean_m_s3": mean(k["gt_after"]),
                    "peak_quiet_window_median_m_s3": median(k["gt_quiet"]),
                    "ratio": ratio(k["gt_after"], k["gt_quiet"])}}
