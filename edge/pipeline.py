"""The one per-frame path from tracker signals to a full-body pose, with SSI.

`edge eval`, `edge run` and `edge replay` drive this object; they differ only in where frames come
from and where poses go. Per frame t:

  body points -> features -> decoder (N samples + a transition row, one batched call)
  -> FK hung from the tracked head -> foot-contact locks and leg IK, arm IK -> FK
  -> criteria on frame t (plausibility, targets, obstacles, extra IMUs) -> SSI decision at t
  -> output frame t - tau, its pose made again from what the look-ahead ring buffer keeps.

With the compiled core and the default criteria that is four C calls around the two ONNX Runtime
calls (ep_frame_inputs, ep_frame_poses, ep_frame_costs after the autoencoder: the costs and the SSI
test, ep_emit); the numpy stages in this file are the reference they are tested against and the
fallback without a compiler.

Two ways through a frame, chosen once: CompiledFrame, the fused C calls the board runs, and
NumpyFrame, the numpy reference they are tested against (and the fallback without a compiler).
SSI's decisions (the outlier test, the best other sample, the move's schedule, the look-ahead ring)
are edge.ssi; this file does the decoding and posing they ask for.

Adaptive N: buffers are sized for `max_samples` once; `set_samples(n)` runs the first n of them
from then on (edge.governor decides n from the frame times). Dropping the shown sample reuses the
SSI transition; a revived sample starts from the shown sample's GRU state, so nothing pops.
"""
import ctypes
import time
from dataclasses import dataclass, field

import numpy as np

from edge import native, quat
from edge.criteria import Composite, FrameContext, PhysicalPlausibility, Plausibility
from edge.features import NUM_POINT_FEATURES, body_points, features, heading, imu_features
from edge.imus import IMU_JOINTS, NUM_IMUS
from edge.heading import HeadingObserver
from edge.ik import FootLock, apply_limb_ik
from edge.inference import Autoencoder, Decoder, open_jacobian, open_models
from edge.modelfiles import ModelError
from edge.options import PipelineOptions
from edge.physics import INTERSECT_M, floor_lift, lowest_point, support
from edge.plausibility import PlausibilityScorer
from edge.refine import Refiner
from edge.signals import EYE_OFFSET, GRIP_OFFSET, Signals
from edge.ssi import LookaheadBuffer, Switcher, switch_to, transition_weight
from edge.skeleton import (ANKLES, HEAD, JOINT, LEVELS, NUM_JOINTS, NUM_PREDICTED, OFFSETS, PARENTS, PELVIS_TO_HEAD,
                           TOES, fk)

# Legs (foot locks) and arms (controllers) solved in one batched IK call.
LIMB_CHAINS = np.array([[JOINT[f"{s}_{a}"], JOINT[f"{s}_{b}"], JOINT[f"{s}_{c}"]]
                        for a, b, c in (("hip", "knee", "ankle"), ("shoulder", "elbow", "wrist")) for s in "lr"])
LIMB_POLES = np.array([[0.0, 0.0, 1.0]] * 2 + [[0.0, 0.0, -1.0]] * 2)   # knees bend forward, elbows back
NECK, SPINE, CHEST = JOINT["neck"], JOINT["spine"], JOINT["chest"]
_FRAME_INPUTS = ("waist_m", "anchor", "wrists", "hand_m", "head_m", "seg_m", "seg_flag")  # a frame's inputs to FK and IK, in ep_row_pose's order
POSITION_LIMIT_M = 30.0     # a tracked position farther out is no tracked space's (step refuses it; POSE_FRAME's root ends at 32.767 m)
# The parts of a live frame, in order; with `timing` on, step() stamps the thread CPU clock after each
# (Pipeline.stage_ns[k + 1] - stage_ns[k] is stage k's time; `edge profile` reads them).
STAGES = ("features", "decoder", "poses", "criteria", "selection", "emit")


@dataclass
class Pose:
    """One output frame: world joint positions [J,3] (m), local joint rotations [J,3,3], foot contacts [2]."""
    frame: int = -1
    positions: np.ndarray = field(default_factory=lambda: np.zeros((NUM_JOINTS, 3)))
    rotations: np.ndarray = field(default_factory=lambda: np.zeros((NUM_JOINTS, 3, 3)))
    contacts: np.ndarray = field(default_factory=lambda: np.zeros(2))
    sample: int = 0
    transition: bool = False


def latent_scale(selection):
    """The spread of the SSI samples' latents, as a multiple of the prior's (a manifest's or --selection's
    `latent_scale`; 1 when it has none). Anything but a number in (0, 4] is refused with the fix."""
    x = selection.get("latent_scale", 1.0)
    if isinstance(x, bool) or not isinstance(x, (int, float)) or not 0.0 < x <= 4.0:
        raise ModelError(f"selection latent_scale must be a number in (0, 4], got {x!r}: fix the model manifest's "
                         "\"selection\" (1.0 draws the samples at the prior's own spread)")
    return float(x)


def fk_with_segments(local, world, pos, seg_m, seg_flag):
    """edge.skeleton.fk for rows [R,J,...] (root at the origin) in which joint j's world rotation is
    its IMU's measurement seg_m[j] where seg_flag[j] > 0, blended with the decoder's in 6D by the flag
    (a fading IMU hands its segment back smoothly), and its local rotation follows. The IMUs fix the
    segments' directions; the body still hangs from the head (DragPoser's sensors as constraints)."""
    world[:, 0], pos[:, 0] = local[:, 0], 0.0
    for idx in LEVELS:
        par = PARENTS[idx]
        world[:, idx] = world[:, par] @ local[:, idx]
        pos[:, idx] = pos[:, par] + (world[:, par] @ OFFSETS[idx][..., None])[..., 0]
        hit = idx[seg_flag[idx] > 0]
        if len(hit):
            f = seg_flag[hit][:, None]
            blend = (1 - f) * quat.matrix_to_6d(world[:, hit]) + f * quat.matrix_to_6d(seg_m[hit])
            world[:, hit] = quat.matrix_from_6d(blend)
            local[:, hit] = np.swapaxes(world[:, PARENTS[hit]], -1, -2) @ world[:, hit]


def supported_contacts(contacts, positions):
    """The decoder's foot contacts [2] as far as each foot of the pose [J,3] is on the floor to bear them
    (edge.physics.support): a foot in the air is not in contact, whatever the contact head says."""
    toe_drop = positions[TOES, 1] - positions[ANKLES, 1]
    return contacts * support(lowest_point(positions[ANKLES, 1], toe_drop))


def midway_rotation(a, b):
    """The rotation halfway between a and b [3,3]: the mean of their 6D, Gram-Schmidt-ed back."""
    return quat.matrix_from_6d(0.5 * (quat.matrix_to_6d(a) + quat.matrix_to_6d(b)))


def ring_runs(first, K, slots):
    """Ring slots first, first + 1, ... (K of them, modulo slots) as at most two runs of slices:
    ((ring slice, row slice), ...), rows counting from 0."""
    n1 = min(K, slots - first)
    if n1 == K:
        return ((slice(first, first + K), slice(0, K)),)
    return ((slice(first, slots), slice(0, n1)), (slice(0, K - n1), slice(n1, K)))


def ease(w, x, y, scratch, out):
    """out = (1 - a) * x + a * y for weights w = [1 - a, a] laid out as x, in float64 scratch [2,...] and
    cast into out once: numpy's (1 - a) * x + a * y for float64 weights, without temporaries."""
    scratch[0], scratch[1] = x, y           # cast first: a mixed-dtype ufunc would allocate a cast buffer
    np.multiply(w[0], scratch[0], out=scratch[0])
    np.multiply(w[1], scratch[1], out=scratch[1])
    np.add(scratch[0], scratch[1], out=scratch[0])
    if out is not scratch[0]:
        out[...] = scratch[0]


def torso_segments(seg_m, seg_flag, waist_m, head_m):
    """With the chest measured, the two torso segments no IMU sees follow from those that are: the
    spine's halfway between the waist and the chest, the neck's halfway between the chest and the
    headset, at the chest's flag (fk_with_segments then sets them). The body hangs from the head
    along this chain, so it places the pelvis."""
    seg_flag[SPINE] = seg_flag[NECK] = seg_flag[CHEST]
    if seg_flag[CHEST] > 0:
        seg_m[SPINE] = midway_rotation(waist_m, seg_m[CHEST])
        seg_m[NECK] = midway_rotation(seg_m[CHEST], head_m)


class FrameBuffers:
    """The memory a frame works in, allocated once and shared by the pipeline and its frame path
    (NumpyFrame or CompiledFrame, which get it explicitly): every row's FK and IK (the N samples, the
    transition row, the look-ahead's recompute), one frame's tracker inputs laid out for the C calls
    (`frame_in`, with a named view of each signal in `inputs`), and a foot target's slots."""

    def __init__(self, rows, lookahead, N, imus, arm_ik, ring):
        """rows: the decoder's rows; ring: the look-ahead ring (each slot's waist rotation is every
        sample's pelvis); imus: the extra IMUs the model reads (0: their inputs are not loaded)."""
        R = max(rows, lookahead + 1)
        self.local = np.zeros((R, NUM_JOINTS, 3, 3))
        self.world = np.zeros((R, NUM_JOINTS, 3, 3))
        self.pos = np.zeros((R, NUM_JOINTS, 3))
        self.zero3 = np.zeros(3)
        self.quats = np.zeros((4, 4))
        self.targets = np.zeros((R, 2, 3))            # foot goals and IK weights, per row
        self.weights = np.zeros((R, 2))
        self.limb_targets = np.zeros((R, 4, 3))
        self.limb_weights = np.zeros((R, 4))
        self.limb_weights[:, 2:] = 1.0 if arm_ik else 0.0
        self.limb_ends = np.zeros((R, 4, 3, 3))
        self.floor_lift = np.zeros((R, 2))           # how far the floor lifted each row's feet (m), per frame
        self.rest6d = np.tile(np.array([1, 0, 0, 0, 1, 0], np.float32), NUM_PREDICTED)   # the rest pose's 6D
        self.toe_offsets = OFFSETS[TOES][:, :, None]
        # Every sample's pelvis is the waist IMU's rotation: a read-only [N,3,3] view of slot s's.
        self.pelvis = [np.broadcast_to(ring.waist_m[k], (N, 3, 3)) for k in range(lookahead + 1)]

        # One frame's tracker signals in (the extra IMUs' orientations and flags after the 25): the C
        # calls' input, and what step() checks before anything uses it (path.inputs).
        self.frame_in = np.zeros(25 + 5 * NUM_IMUS)
        self.good_in = np.zeros_like(self.frame_in)     # the last frame that passed
        self.inputs = {k: self.frame_in[i:j].reshape(shape) for k, i, j, shape in (
            ("head_pos", 0, 3, (3,)), ("head_rot", 3, 7, (4,)), ("hand_pos", 7, 13, (2, 3)),
            ("hand_rot", 13, 21, (2, 4)), ("waist_rot", 21, 25, (4,)),
            ("imu_rot", 25, 25 + 4 * NUM_IMUS, (NUM_IMUS, 4)), ("imu_flag", 25 + 4 * NUM_IMUS, 25 + 5 * NUM_IMUS, (NUM_IMUS,)))}
        # The Signals fields _load_frame_in copies, each with its [1,...] view of _frame_in.
        self.input_fields = [(k, v[None]) for k, v in self.inputs.items() if imus or not k.startswith("imu")]
        # A live target on a foot of the refined row: the row (-1: none), per foot the target's joint
        # (ankle or toe), point and pull on the leg's IK goal (edge.refine.Refiner.foot_pull).
        self.target_row = np.full(1, -1, np.int64)
        self.target_joint = np.array(ANKLES, np.int64)
        self.target_goal = np.zeros((2, 3))
        self.target_weight = np.zeros(2)


class Pipeline:
    def __init__(self, options=None, models=None, criteria=None):
        """options: a PipelineOptions (edge.options; the defaults when None); models: the model folder
        (the shipped models/ when None); criteria: SSI's selection criteria in place of the model's."""
        o = self.options = PipelineOptions() if options is None else options
        # The newest frame's pose by default: tau frames of look-ahead put the body tau / fps behind the
        # person (167 ms at tau = 10, 60 Hz), which is for offline use (recording, edge eval --lookahead).
        self.max_samples = o.samples    # allocated for; `samples` is how many run now (adaptive N: set_samples)
        self.samples, self.fps, self.body_scale = o.samples, o.fps, o.body_scale
        self.lookahead, self.transition = o.lookahead, o.transition
        self.ssi = o.ssi and o.samples > 1
        self.foot_ik, self.arm_ik = o.foot_ik, o.arm_ik
        self.manifest, dec_session, ae_session = open_models(models, o.threads, o.precision)
        self._open(dec_session, ae_session, o.use_native)
        self._choose(o.selection or self.manifest.get("selection", {}), criteria, o.use_native, o.seed)
        self._allocate_ssi()
        self.bufs = FrameBuffers(self.rows, self.lookahead, self.samples, self.imus, o.arm_ik, self.buffer)
        self.out = Pose()
        self._choose_paths(dec_session, models, o.use_native, o.threads)
        self.reset()

    def _open(self, dec_session, ae_session, use_native):
        """The decoder (N rows and a transition row), its look-ahead recompute, the autoencoder and scorer."""
        m, N, lookahead = self.manifest, self.samples, self.lookahead
        # what runs: int8 falls back to fp32 where its start-up self-check fails (edge.int8check)
        self.precision, self.precision_note = m["precision"], m["precision_note"]
        # The decoder's input: the 24 point features, and the extra IMUs' 49 when the model reads them.
        self.n_features = m["features"]
        self.imus = NUM_IMUS if self.n_features > NUM_POINT_FEATURES else 0
        # A worn IMU also sets its segment's world rotation after the decoder (fk_with_segments).
        self.segments = bool(self.options.segments and self.imus)
        self.rows = N + 1 if N > 1 else N   # the extra row carries a live transition
        self.decoder = Decoder(dec_session, self.rows, m["latent"], m["hidden"], m["features"])
        self.recompute = Decoder(dec_session, lookahead + 1, m["latent"], m["hidden"], m["features"], recurrent=False)
        self.autoencoder = Autoencoder(ae_session, N)
        self.threshold = m["plausibility_threshold_m"]
        self.scorer = PlausibilityScorer(self.autoencoder, self.threshold, use_native)

    def _choose(self, chosen, criteria, use_native, seed):
        """SSI's selection: its criteria, margins and homing, and the samples' latents (`chosen`: the settings)."""
        m, N = self.manifest, self.samples
        self.criteria = Composite(criteria if criteria is not None else self.default_criteria(chosen, use_native))
        self.switch_margin = float(chosen.get("switch_margin", 0.0))
        # Homing: a shown sample other than sample 0 (the prior mean, the most accurate on average) moves
        # back to it once sample 0 has cost no more than the shown one (+ home_margin) for home_after
        # frames in a row: SSI leaves the mean to get out of a fault and returns when the fault is past.
        # Part of the selection the model's criteria were tuned with: off when the caller brings its own.
        self.home_after = int(chosen.get("home_after", 0)) if criteria is None else 0
        self.home_margin = float(chosen.get("home_margin", 0.0))

        # N=1 is the plain CVAE at the prior mean; more samples draw fixed latents once (SSI 3.2), and
        # sample 0, the one shown first, stays the prior mean: SSI moves away from what N=1 shows only
        # when that is an outlier. The draws are the prior's at `latent_scale` times its spread (a
        # sampling temperature, chosen on val with the selection weights: see the manifest).
        self.latent_scale = latent_scale(chosen)
        self.latents = np.zeros((N, m["latent"]), np.float32)
        if N > 1:
            self.latents[1:] = self.latent_scale * np.random.default_rng(seed).standard_normal((N - 1, m["latent"]))
        self.decoder.latent[:N] = self.latents

    def _allocate_ssi(self):
        """The look-ahead ring, the switcher, a switch's recompute scratch and the foot locks."""
        m, N, lookahead, transition = self.manifest, self.samples, self.lookahead, self.transition
        self.buffer = LookaheadBuffer(lookahead + 1, N, m["hidden"], m["features"], self.decoder.rot6d.shape[1],
                                      NUM_JOINTS)
        self.switcher = Switcher(lookahead, transition)
        # A switch's recompute works in these (_recompute_transition): ring slots, the move's weights, and
        # float64 scratch for each eased quantity, for up to K = tau + 1 frames.
        K, H, L = lookahead + 1, m["hidden"], m["latent"]
        w = transition_weight(np.arange(K), transition)
        w = np.stack([1 - w, w])                # [2,K]: 1 - a and a at each step of a move
        self._switch_scratch = {"latent": np.zeros((2, K, L)), "hidden_in": np.zeros((2, K, H), np.float32),
                                "hidden": np.zeros((2, K, H)), "goal_in": np.zeros((2, K, 2, 3)),
                                "goal": np.zeros((2, K, 2, 3)), "w_latent": np.repeat(w[..., None], L, 2),
                                "w_hidden": np.repeat(w[..., None], H, 2), "w_goal": np.tile(w[..., None, None], (1, 1, 2, 3))}
        self.feet = FootLock(N)

    def _choose_paths(self, dec_session, models, use_native, threads):
        """The compiled core or the numpy reference, and the heading observer and refiner if asked."""
        m, fps, o = self.manifest, self.fps, self.options
        # The compiled core (edge/native) runs the whole frame around the two ONNX calls when a C
        # compiler is there; NumpyFrame is the reference and the fallback.
        self.native = native.load() if use_native else None
        self.reference = NumpyFrame(self, self.bufs)
        self.path = CompiledFrame(self, self.bufs, self.native) if self.native else self.reference
        self.timing, self.stage_ns = False, np.zeros(len(STAGES) + 1, np.int64)
        # The extra IMUs' heading observer (edge.heading), on when IMUs are worn and options.heading is set.
        self.heading = HeadingObserver(fps, o.heading) if o.heading is not None and self.imus else None
        if self.heading is not None:
            self.heading.decoder_fk = self._decoder_row_fk
        # Latent refinement of the shown sample (edge.refine), when options.refine is set.
        self.refiner = None
        if o.refine is not None:
            compiled = (self.native, self.path.core, lambda: self._slot_now) if self.native else None
            self.refiner = Refiner(dec_session, m, self._forward_rows, o.refine, fps, compiled=compiled,
                                   jacobian_session=open_jacobian(models, threads, self.precision))

    def default_criteria(self, selection, use_native=True):
        """SSI's default selection cost: the autoencoder's plausibility score, plus the physical one
        (edge.criteria.PhysicalPlausibility) at the weights of `selection` (the manifest's, chosen on val
        for this model, or one given; without a "physical" entry the autoencoder alone, at weight 1)."""
        w = selection
        out = [Plausibility(self.scorer, w.get("plausibility", 1.0))]
        if w.get("physical"):
            p = w["physical"]
            out.append(PhysicalPlausibility(p.get("weight", 1.0), p.get("floor", 1.0), p.get("legs", 1.0),
                                            p.get("support", 1.0), use_native,
                                            p.get("clearance", INTERSECT_M)))
        return out

    @property
    def decoder(self):
        return self._decoder

    @decoder.setter
    def decoder(self, dec):
        """A decoder may be swapped in after construction (bench/reference.py runs a PyTorch one): the
        compiled core then reads and writes the new one's buffers."""
        self._decoder = dec
        if getattr(self, "path", None) is not None:
            self.path.bind_decoder(dec)

    # SSI's state, as edge.ssi.Switcher keeps it.
    current = property(lambda self: self.switcher.current)
    trans = property(lambda self: self.switcher.trans)
    trans_end = property(lambda self: self.switcher.trans_end)
    switches = property(lambda self: self.switcher.switches)
    switch_count = property(lambda self: self.switcher.switch_count)

    # ------------------------------------------------------------------ state
    def reset(self):
        self.decoder.reset()
        self.decoder.latent[:self.max_samples] = self.latents     # refinement moved the shown one
        self.feet.reset()
        self.path.reset()
        self._pending = None        # a change of N waiting for a transition to be sent
        self.buffer.frame[:] = -1
        self.buffer.override[:] = False
        self.t = -1
        self.switcher.reset()
        self._home_run = 0
        self.state_resets = 0       # decoder rows whose GRU state or output went non-finite (see _heal)
        self.inputs_held = 0        # frames whose signals were non-finite or out of range (see step)
        if self.heading is not None:
            self.heading.reset()

    # ------------------------------------------------------------------ per frame
    def step(self, sig):
        """Feed one frame of Signals (T=1). Returns the Pose for frame t - tau, or None while the buffer fills."""
        timing, mark = self.timing, self.stage_ns
        if timing:
            mark[0] = time.thread_time_ns()
        self.t += 1
        t, b, N, sw = self.t, self.buffer, self.samples, self.switcher
        s = t % b.slots
        b.frame[s] = t
        b.override[s] = False
        dec = self.decoder
        self._load_frame_in(sig)
        if self.heading is not None:    # the IMUs' headings corrected before anything reads them (edge.heading)
            sig = self.heading.correct_frame(self.bufs.inputs, sig)
        # During a move the spare row carries it: both latents and GRU states eased (path.inputs does it).
        live = sw.live(t)
        blend = (sw.trans[0], sw.trans[1], sw.weight(t)) if live else None
        # Features and tracker matrices into slot s and the decoder, if the frame is sane: finite, and
        # inside POSITION_LIMIT_M of the origin (no play space is larger). One that a range check upstream
        # did not catch is replaced by the last good one.
        if not self.path.inputs(sig, s, N, blend):
            sig = self._held_frame()
            self.path.inputs(sig, s, N, blend)
        if timing:
            mark[1] = time.thread_time_ns()
        dec.step()
        if self.refiner is not None:
            self._refine(s, N, sw.current)
        if timing:
            mark[2] = time.thread_time_ns()

        # Post-processing for every row at once; the transition row (row N) blends the two samples' foot
        # goals (not lock positions, which are stale for a foot that is free) and, like the samples, runs
        # the leg IK at weight 1: the goals already carry each lock's pull, so the row's first and last
        # frames are the two samples' own poses.
        fused = self.criteria.criteria == self.path.fused_criteria     # the default criteria: judged in one C call
        keep_world = not fused and self.criteria.needs_world_rot  # every joint's world rotation, only if a criterion asks
        rows = N + 1 if live else N
        if not self.path.poses(s, rows, N, blend, keep_world):   # a decoder row went non-finite: nothing was done
            self._heal(dec, s)
            self.path.poses(s, rows, N, blend, keep_world)
        if live:
            b.override[s] = True
            b.trans_row[s] = N
        if self.heading is not None:    # each IMU against its reference (edge.heading), at the observer's rate
            self.heading.observe_frame(self.t, self.bufs.inputs, s, sw.current)
        if timing:
            mark[3] = time.thread_time_ns()

        # Judge frame t, the newest, and decide (3.2.4: detection at t + tau relative to the output). A new
        # switch waits until the last transition has been sent, so transitions never overlap.
        ask = (self._pending is None and self.ssi and N > 1 and sw.free(t)
               and not (self.refiner is not None and self.refiner.holds(t)))     # refinement owns the shown sample
        n = -1
        if N > 1:
            c = sw.current if ask else -1
            n = self.path.judge(s, N, c) if fused else self._judge(sig, s, N, c, keep_world)
        if timing:
            mark[4] = time.thread_time_ns()
        if n < 0 and ask and self.home_after and sw.current != 0:
            n = self._homeward(s, sw.current)
        if self._pending is not None:
            self._apply_samples(t, s)
        elif n >= 0:
            self._start_transition(n, t)
        if timing:
            mark[5] = time.thread_time_ns()
        pose = self._emit(t - self.lookahead)
        if timing:
            mark[6] = time.thread_time_ns()
        return pose

    def _homeward(self, s, c):
        """0 when the shown sample c should move back to sample 0 (see home_after), else -1."""
        cost = self.buffer.cost[s]
        self._home_run = self._home_run + 1 if cost[0] <= cost[c] + self.home_margin else 0
        if self._home_run < self.home_after:
            return -1
        return 0

    def _refine(self, s, N, c):
        """edge.refine on the shown sample's row of this frame: its latent moves (and stays moved for
        the next frame), and its decode (6D, contacts, the GRU state it wrote) replaces the row's."""
        if not self.refiner.busy():
            self._set_target_row(-1)
            return
        dec, f = self.decoder, self.feet
        self._slot_now = s
        out = self.refiner.refine(self.t, dec.latent[c], self.latents[c], dec.hidden[dec.last_read][c], dec.features[0],
                                  self.buffer.seg_m[s], self.buffer.seg_flag[s], f.lock_pos[c], f.weight[c], row=c)
        if out is not None:
            dec.rot6d[c], dec.contacts[c], dec.state[c] = out
        pulls = self.refiner.foot_pull(self.t, self.bufs.target_joint, self.bufs.target_goal, self.bufs.target_weight)
        self._set_target_row(c if pulls else -1)

    def _set_target_row(self, row):
        """The row whose leg goals a foot target pulls this frame (-1: none), for both paths' foot goals."""
        if row != self.bufs.target_row[0]:
            self.bufs.target_row[0] = row
            self.path.set_target_row(row)

    def _decoder_row_fk(self, s, row, out):
        """FK of decoder row `row` of ring slot s without the IMU override, into out (the heading
        observer's reference when it is the decoder)."""
        self.path.forward_rows(s, self.buffer.rot6d[s, row:row + 1], 1, False, out)

    def _forward_rows(self, rot6d, rows, segments, out):
        """FK of `rows` decoder rows (rot6d [R,D] float32) against the live frame's inputs, into out =
        (local, world, pos): the refiner's forward."""
        self.path.forward_rows(self._slot_now, rot6d, rows, segments, out)

    def _judge(self, sig, s, N, c, keep_world):
        """Any criteria (edge.criteria, composed): frame t's costs into ring slot s, then the sample to
        move to from c (c < 0: not asked). The default criteria take CompiledFrame.judge instead."""
        dec = self.decoder
        ctx = FrameContext(self.t, self.bufs.pos[:N], self.bufs.world[:N] if keep_world else None, self.bufs.pelvis[s][:N],
                           ae_ready=self.path.ae_ready, contacts=dec.contacts[:N], floor_lift=self.bufs.floor_lift[:N])
        if self.criteria.needs_imu and self.imus:       # the extra IMUs the frame has, for SensorAgreement
            worn = np.flatnonzero(sig.imu_flag[0] > 0)
            m = quat.to_matrix(sig.imu_rot[0, worn])
            ctx.imu = {int(IMU_JOINTS[k]): m[i] for i, k in enumerate(worn)}
            ctx.imu_weight = {int(IMU_JOINTS[k]): float(sig.imu_flag[0, k]) for k in worn}
        self.buffer.cost[s, :N] = self.criteria.cost(ctx)
        return self.path.switch_to(s, c, self.switch_margin) if c >= 0 else -1

    def _held_frame(self):
        """Stand the last good frame in for this one (counted in inputs_held); before any, a neutral
        one: standing at the origin, facing +Z, no extra IMUs."""
        self.inputs_held += 1
        if not self.bufs.good_in.any():
            self.bufs.good_in[:] = 0.0
            self.bufs.good_in[[1, 3, 13, 17, 21]] = [1.6, 1.0, 1.0, 1.0, 1.0]
            self.bufs.good_in[7:13] = [0.3, 1.0, 0.2, -0.3, 1.0, 0.2]
        np.copyto(self.bufs.frame_in, self.bufs.good_in)
        v = self.bufs.inputs
        return Signals(v["head_pos"][None].copy(), v["head_rot"][None].copy(), v["hand_pos"][None].copy(),
                       v["hand_rot"][None].copy(), v["waist_rot"][None].copy(), np.zeros((1, 3)),
                       v["imu_rot"][None].copy(), v["imu_flag"][None].copy())

    def _heal(self, dec, s):
        """Rows whose GRU state or output went non-finite (an input no range check caught, or a state
        that blew up): their state goes back to the start-of-clip state, and their output for this
        frame is the row's previous one, so no NaN reaches a pose; the row recovers within a few
        frames from there. Counted in state_resets. Off the per-frame path: only runs on a bad row."""
        R = dec.rows
        bad = ~(np.isfinite(dec.state[:R]).all(1) & np.isfinite(dec.rot6d[:R]).all(1) & np.isfinite(dec.contacts[:R]).all(1))
        prev = self.buffer.slot(self.t - 1)
        held = self.buffer.frame[prev] == self.t - 1
        for r in np.flatnonzero(bad):
            dec.state[r] = 0.0
            dec.rot6d[r] = self.buffer.rot6d[prev, r] if held else self.bufs.rest6d
            dec.contacts[r] = 0.0
        if not np.isfinite(dec.features).all():     # the ring must not keep what a recompute would re-run
            self.buffer.features[s] = self.buffer.features[prev] if held else 0.0
        self.state_resets += int(bad.sum())

    def _load_frame_in(self, sig):
        """One frame (T=1) of Signals into _frame_in, the C calls' input layout (no temporaries)."""
        for name, dst in self.bufs.input_fields:
            dst[...] = getattr(sig, name)       # not np.copyto: its Python wrapper costs 3x as much

    def set_samples(self, n):
        """Adaptive N: run the first n (1..max_samples) samples, each keeping its own latent.

        Takes effect after this frame, unless a running transition still reads a sample that would
        go (then when it no longer does). If the shown sample is not among the first n, the output
        first moves to the best of them with the SSI transition (once any running one has been sent)
        and the smaller N applies when that transition no longer reads it. Returns the N asked for."""
        n = int(min(max(n, 1), self.max_samples))
        self._pending = None if n == self.samples else n
        return n

    # ------------------------------------------------------------------ targets (edge.refine)
    @property
    def takes_targets(self):
        """Whether a target can move the body: refinement is on with its targets term."""
        return self.refiner is not None and self.refiner.term("targets") is not None

    def add_target(self, joint, position, radius, start=0, frames=1, key=None):
        """A point (canonical body, metres) that `joint` should reach within `radius`, live for `frames`
        frames from `start` frames after the next one; refused with a reason (edge.refine counts it) when
        it is not finite, not a joint, or beyond reach of the shown body's pelvis."""
        first = self.t + 1 + start
        out = self.out
        self.refiner.add_target(joint, position, radius=radius, first=first, last=first + max(frames - 1, 0),
                                pelvis=out.positions[0] if out.frame >= 0 else None, key=key)

    def remove_target(self, key):
        self.refiner.remove_target(key)

    def set_refine_steps(self, k):
        """Refinement steps a frame from the next frame on (edge.governor moves N and K together). At
        K = 0 a live target no longer moves the latent (a foot target still pulls the leg IK) and a
        latent that was moved is let go. Without a refiner there is nothing to set."""
        if self.refiner is not None:
            self.refiner.steps = max(int(k), 0)

    def flush(self):
        """Poses for the frames still in the look-ahead buffer (end of a take)."""
        out = []
        for o in range(self.t - self.lookahead + 1, self.t + 1):
            if o >= 0:
                p = self._emit(o)
                out.append(Pose(p.frame, p.positions.copy(), p.rotations.copy(), p.contacts.copy(), p.sample, p.transition))
        return out

    # ------------------------------------------------------------------ SSI moves and N
    def _apply_samples(self, t, s):
        n, N, sw = self._pending, self.samples, self.switcher
        c = sw.current
        if n < N and c >= n:        # the shown sample would go: move to the best kept one first
            if sw.free(t):
                self._start_transition(int(np.argmin(self.buffer.cost[s, :n])), t)
            return
        if n < N and sw.trans is not None and t < sw.trans_end and sw.trans[0] >= n:
            return                  # the live transition row still interpolates from that sample
        if n > N:
            self._revive(N, n)
        self.samples, self._pending = n, None
        self.decoder.resize(n + 1)
        self.autoencoder.resize(n)

    def _revive(self, lo, hi):
        """Samples lo..hi-1 come back with their own latents, from the shown sample's GRU state and
        foot locks (their old state is stale); their buffered frames copy the shown sample's, so a
        transition to one of them can be recomputed over the look-ahead like any other."""
        c, b, dec = self.switcher.current, self.buffer, self.decoder
        dec.latent[lo:hi] = self.latents[lo:hi]
        dec.state[lo:hi] = dec.state[c]
        self.feet.copy_rows(c, slice(lo, hi))
        for a in (b.hidden_in, b.rot6d, b.contacts, b.leg_goal, b.leg_weight, b.lock_weight):
            a[:, lo:hi] = a[:, c:c + 1]

    def _start_transition(self, n, t):
        c = self.switcher.current
        if self.refiner is not None:        # the sample left behind goes back to its own latent
            self.decoder.latent[c] = self.latents[c]
        self._home_run = 0
        s0 = self.switcher.start(n, t)
        self._recompute_transition(c, n, s0, self.transition, t)
        # The sample moved to takes the shown one's foot locks: a planted foot stays where the user sees
        # it, instead of the move's eased goals sliding it to where the other sample had planted it.
        self.feet.copy_rows(c, n)

    def _recompute_transition(self, c, n, s0, T, t):
        """Re-run the buffered frames s0..t along the transition (one batched decoder call); their
        poses are made when they are sent. Each eased as (1 - a) x + a y in float64 (a: the move's
        weights at those frames), in preallocated scratch: a switch makes no arrays."""
        b, rc, N, sc = self.buffer, self.recompute, self.samples, self._switch_scratch
        K = min(t, s0 + T - 1) - s0 + 1
        runs = ring_runs(s0 % b.slots, K, b.slots)
        h, g = sc["hidden_in"], sc["goal_in"]
        for ring, rows in runs:                              # gather the frames' inputs (at most two runs)
            rc.features[rows] = b.features[ring]
            h[0, rows], h[1, rows] = b.hidden_in[ring, c], b.hidden_in[ring, n]
            g[0, rows], g[1, rows] = b.leg_goal[ring, c], b.leg_goal[ring, n]
        # a and 1 - a at the move's steps 0..K-1, laid out as each quantity (a broadcast would allocate)
        ease(sc["w_latent"][:, :K], self.latents[c], self.latents[n], sc["latent"][:, :K], rc.latent[:K])
        ease(sc["w_hidden"][:, :K], h[0, :K], h[1, :K], sc["hidden"][:, :K], rc.hidden[0][:K])
        goal = sc["goal"][:, :K]
        ease(sc["w_goal"][:, :K], g[0, :K], g[1, :K], goal, goal[0])
        rc.step()
        for ring, rows in runs:                              # and the spare row N of each frame
            b.override[ring] = True
            b.trans_row[ring] = N
            b.rot6d[ring, N] = rc.rot6d[rows]
            b.contacts[ring, N] = rc.contacts[rows]
            b.leg_goal[ring, N] = goal[0, rows]
            b.leg_weight[ring, N] = 1.0

    # ------------------------------------------------------------------ output
    def _emit(self, o):
        if o < 0:
            return None
        b, p = self.buffer, self.out
        s = b.slot(o)
        p.frame = o
        p.transition = bool(b.override[s])
        if p.transition:
            row = int(b.trans_row[s])
            p.sample = self.switcher.shown_during_move()
        else:
            row = p.sample = self.switcher.sample_at(o)
        self.path.emit(s, row, p)
        return p

    def pose_from_buffer(self, frame, row, positions=None, rotations=None):
        """The pose of pose row `row` (a sample, or N for a transition) of a buffered frame, made again
        from what the buffer keeps (by the numpy reference): world positions [J,3] and local rotations
        [J,3,3], into the given arrays or new ones."""
        s = self.buffer.slot(frame)
        if self.buffer.frame[s] != frame:
            raise ValueError(f"frame {frame} is not in the look-ahead buffer")
        positions = np.zeros((NUM_JOINTS, 3)) if positions is None else positions
        rotations = np.zeros((NUM_JOINTS, 3, 3)) if rotations is None else rotations
        return self.reference.row_pose(s, row, positions, rotations)


class NumpyFrame:
    """The numpy reference of a frame's stages: what the compiled core is tested against, and what
    runs without a C compiler. It works in the pipeline's FrameBuffers and ring buffer."""

    ae_ready = None             # the scorer whose autoencoder input this path prepares (none: the scorer does)
    fused_criteria = None       # the criteria this path judges in one call (none: each judges itself)

    def __init__(self, pipe, bufs):
        self.p, self.bufs = pipe, bufs

    def reset(self):
        self.prev_points = None     # the previous frame's body points (velocity features)

    def bind_decoder(self, dec):
        pass

    def set_target_row(self, row):
        pass                        # foot_goals reads the pipeline's _target_row

    def sane(self):
        v, head, hands = self.bufs.frame_in, self.bufs.inputs["head_pos"], self.bufs.inputs["hand_pos"]
        total = float(v.sum())
        return (total - total == 0.0 and -POSITION_LIMIT_M < head.min() and head.max() < POSITION_LIMIT_M
                and -POSITION_LIMIT_M < hands.min() and hands.max() < POSITION_LIMIT_M)

    def inputs(self, sig, s, N, blend):
        """Body points, features and tracker matrices of one frame into ring slot s and the decoder, and
        the spare row N's latent and GRU state eased between a live move's two samples (blend: from,
        to, weight; or None). False, doing nothing, when the frame is not sane (the pipeline's
        _frame_in); a frame that is is kept in _good_in."""
        p, b, dec = self.p, self.p.buffer, self.p.decoder
        if not self.sane():
            return False
        np.copyto(self.bufs.good_in, self.bufs.frame_in)
        if blend is not None:
            c, n, a = blend
            a = np.float64(a)       # eased in float64, rounded once to the decoder's float32 (as ep_frame_inputs)
            dec.latent[N] = (1 - a) * p.latents[c] + a * p.latents[n]
            dec.state[N] = (1 - a) * dec.state[c] + a * dec.state[n]
        points, waist_rot = body_points(sig, p.body_scale)
        points, waist_rot = points[0], waist_rot[0]
        prev = points if self.prev_points is None else self.prev_points
        self.prev_points = points
        yaw_q = heading(waist_rot)
        feat = features(points, prev, yaw_q, p.fps)
        if p.imus:
            feat = np.concatenate([feat, imu_features(sig.imu_rot[0], sig.imu_flag[0], yaw_q)])
        q = self.bufs.quats                         # waist, hands, head: one to_matrix call
        q[0], q[1:3], q[3] = waist_rot, sig.hand_rot[0], sig.head_rot[0]
        m = quat.to_matrix(q)
        b.features[s] = feat
        b.anchor[s] = points[0]
        b.wrists[s] = points[1:3]
        b.waist_m[s], b.hand_m[s], b.head_m[s] = m[0], m[1:3], m[3]
        if p.segments:
            b.seg_m[s, IMU_JOINTS] = quat.to_matrix(sig.imu_rot[0])
            b.seg_flag[s, IMU_JOINTS] = sig.imu_flag[0]
            torso_segments(b.seg_m[s], b.seg_flag[s], m[0], m[3])
        dec.features[:] = feat
        b.hidden_in[s, :p.samples] = dec.state[:p.samples]
        return True

    def finite(self, dec):
        return bool(np.isfinite(dec.state[:dec.rows]).all() and np.isfinite(dec.rot6d[:dec.rows]).all())

    def poses(self, s, rows, N, blend, keep_world):
        """Every row's pose of frame s: FK, foot locks, the transition row's blended goals, IK; and
        what the ring keeps of them. False, doing nothing, when a decoder row is not finite."""
        p, b, dec = self.p, self.p.buffer, self.p.decoder
        if not self.finite(dec):
            return False
        self.forward(dec.rot6d[:rows], b.waist_m[s], b.anchor[s], b.seg_m[s], b.seg_flag[s])
        if p.foot_ik:
            goal, w = self.foot_goals(N)
            if blend is not None:
                c, n, a = blend
                self.bufs.targets[N] = (1 - a) * goal[c] + a * goal[n]
                self.bufs.weights[N] = 1.0      # like the samples' own: their goals carry the locks' pull
        self.post(rows, b.wrists[s], b.hand_m[s], b.head_m[s])
        b.rot6d[s, :rows] = dec.rot6d[:rows]
        b.contacts[s, :rows] = dec.contacts[:rows]
        b.leg_goal[s, :rows] = self.bufs.targets[:rows]
        b.leg_weight[s, :rows] = self.bufs.weights[:rows]
        b.lock_weight[s, :N] = p.feet.weight[:N]
        return True

    def switch_to(self, s, c, margin):
        return switch_to(self.p.buffer.cost[s, :self.p.samples], c, margin)

    def emit(self, s, row, out):
        self.row_pose(s, row, out.positions, out.rotations)
        out.contacts[:] = supported_contacts(self.p.buffer.contacts[s, row], out.positions)

    def row_pose(self, s, row, positions, rotations):
        """The pose of one row of ring slot s, made again from what the ring keeps."""
        b = self.p.buffer
        self.forward(b.rot6d[s, row][None], b.waist_m[s], b.anchor[s], b.seg_m[s], b.seg_flag[s])
        self.bufs.targets[0], self.bufs.weights[0] = b.leg_goal[s, row], b.leg_weight[s, row]
        self.post(1, b.wrists[s], b.hand_m[s], b.head_m[s])
        positions[:], rotations[:] = self.bufs.pos[0], self.bufs.local[0]
        return positions, rotations

    # ---- the stages
    def forward(self, rot6d, waist_m, anchor, seg_m=None, seg_flag=None, out=None):
        """6D -> local rotations, FK with the waist IMU as root, body hung from the tracked head; the
        segments of worn IMUs take their measured rotations (fk_with_segments; seg_m [J,3,3], seg_flag [J]).
        waist_m [3,3] or per row [R,3,3]; anchor (the tracked head joint) [3] or [R,3]. Writes out =
        (local, world, pos), by default the FrameBuffers' rows."""
        R = len(rot6d)
        loc, W, P = (self.bufs.local[:R], self.bufs.world[:R], self.bufs.pos[:R]) if out is None else out
        loc[:, 0] = waist_m
        quat.matrix_from_6d(rot6d.reshape(R, NUM_PREDICTED, 6), out=loc[:, 1:])
        if seg_flag is not None and seg_flag.any():
            fk_with_segments(loc, W, P, seg_m, seg_flag)
        else:
            fk(loc, self.bufs.zero3, out=(W, P))
        P += anchor[..., None, :] - P[:, HEAD:HEAD + 1]

    def forward_rows(self, s, rot6d, rows, segments, out):
        """forward() of decoder rows against ring slot s's inputs, into out = (local, world, pos)."""
        b = self.p.buffer
        seg = (b.seg_m[s], b.seg_flag[s]) if segments else (None, None)
        self.forward(rot6d[:rows], b.waist_m[s], b.anchor[s], *seg, out=out)

    def foot_goals(self, N):
        """Update the N samples' foot-contact locks from the decoder's contacts and the FK ankles; each
        sample's foot goal (in _targets) is where its lock draws the ankle, so the leg IK runs at weight 1.
        Returns (goals [N,2,3], lock weights [N,2])."""
        p = self.p
        goal, pos = self.bufs.targets[:N], self.bufs.pos
        toe_drop = (self.bufs.world[:N, ANKLES] @ self.bufs.toe_offsets)[..., 1, 0]   # for the locks' floor snap
        lock, w = p.feet.update(p.decoder.contacts[:N], pos[:N, ANKLES], toe_drop)
        ankle = pos[:N, ANKLES]
        np.subtract(lock, ankle, out=goal)
        goal *= w[..., None]
        goal += ankle
        self.bufs.weights[:N] = 1.0
        r = self.bufs.target_row[0]
        if 0 <= r < N:              # a live target on a foot of the refined row pulls its leg goal (edge.refine)
            tw = self.bufs.target_weight
            want = self.bufs.target_goal - (pos[r, self.bufs.target_joint] - pos[r, ANKLES])
            goal[r] += tw[:, None] * (want - goal[r])
        return goal, w

    def post(self, rows, wrists, hand_m, head_m):
        """Leg IK to the foot locks and arm IK to the controllers in one batched call, head to the headset.

        The legs' goals are lifted where an ankle or a toe would be under the floor (edge.physics;
        how far goes to _floor_lift), so foot IK never puts a foot into the floor, and a lock holds
        the foot on it, not under it. wrists [2,3], hand_m [2,3,3], head_m [3,3], or the same per row.
        Updates rotations and positions in place (the IK moves knees, ankles, toes, elbows and wrists).
        """
        p = self.p
        if not (p.foot_ik or p.arm_ik):
            return
        loc, W, P = self.bufs.local[:rows], self.bufs.world[:rows], self.bufs.pos[:rows]
        tgt, wts, ends = self.bufs.limb_targets[:rows], self.bufs.limb_weights[:rows], self.bufs.limb_ends[:rows]
        tgt[:, :2] = self.bufs.targets[:rows]
        tgt[:, 2:] = wrists
        wts[:, :2] = self.bufs.weights[:rows] if p.foot_ik else 0.0
        if p.foot_ik:               # the effective leg goals, lifted clear of the floor, at weight 1
            ankle = P[:, ANKLES]
            tgt[:, :2] = ankle + wts[:, :2, None] * (tgt[:, :2] - ankle)
            lift = floor_lift(tgt[:, :2, 1], (W[:, ANKLES] @ self.bufs.toe_offsets)[..., 1, 0])
            tgt[:, :2, 1] += lift
            wts[:, :2] = 1.0
            self.bufs.floor_lift[:rows] = lift
        ends[:, :2] = W[:, ANKLES]
        ends[:, 2:] = hand_m if p.arm_ik else W[:, LIMB_CHAINS[2:, 2]]
        apply_limb_ik(loc, W, P, PARENTS, LIMB_CHAINS, tgt, wts, LIMB_POLES, ends, OFFSETS)
        P[:, TOES] = P[:, ANKLES] + (W[:, ANKLES] @ self.bufs.toe_offsets)[..., 0]
        if p.arm_ik:
            W[:, HEAD] = head_m
            loc[:, HEAD] = np.swapaxes(W[:, NECK], -1, -2) @ head_m


class CompiledFrame:
    """The frame the board runs: four C calls (edge/native/postproc.c) around the two ONNX Runtime
    calls, each bit-identical to NumpyFrame's stages up to float rounding (tests/test_native.py).
    The addresses they use are found once here: the skeleton, the scratch rows, FootLock's state,
    the ring buffer, the output pose and the decoder's buffers (native.CoreContext)."""

    def __init__(self, pipe, bufs, lib):
        self.p, self.bufs, self.lib = pipe, bufs, lib
        self.ae_ready = self.fused_criteria = None      # set below when the defaults allow (NumpyFrame's say)
        p, N, b = pipe, pipe.max_samples, pipe.buffer
        # Arrays the C calls read by address; held here so they live as long as the pipeline.
        self._c = {"parents": np.ascontiguousarray(PARENTS, np.int64), "offsets": OFFSETS,
                   "chains": np.ascontiguousarray(LIMB_CHAINS, np.int64), "poles": LIMB_POLES,
                   "ankles": np.ascontiguousarray(ANKLES, np.int64), "imu_joints": np.ascontiguousarray(IMU_JOINTS, np.int64)}
        # Every array the core reads or writes is checked once here (dtype, layout, shape); the hot
        # path then passes addresses only.
        J, R = NUM_JOINTS, len(self.bufs.local)
        chk = native.checked_addr
        a = self.addr = {k: chk(v, np.int64 if v.dtype.kind == "i" else np.float64, None, k) for k, v in self._c.items()}
        for k, shape in (("local", (R, J, 3, 3)), ("world", (R, J, 3, 3)), ("pos", (R, J, 3)), ("targets", (R, 2, 3)),
                         ("weights", (R, 2)), ("floor_lift", (R, 2))):
            a[k] = chk(getattr(bufs, k), np.float64, shape, k)
        for k, dtype in (("lock_pos", np.float64), ("locked", np.bool_), ("raw", np.bool_), ("since_release", np.float64),
                         ("weight", np.float64)):      # FootLock's state
            a[k] = chk(getattr(p.feet, k), dtype, (N,) + getattr(p.feet, k).shape[1:], k)
        for arr in vars(b).values():                    # the look-ahead ring
            if isinstance(arr, np.ndarray):
                chk(arr, arr.dtype, None, "ring buffer")
        self._frame_offsets = np.concatenate([EYE_OFFSET[None], GRIP_OFFSET, (PELVIS_TO_HEAD * p.body_scale)[None]])
        self._prev = np.zeros((4, 3))
        a["frame_in"], a["frame_offsets"], a["prev"] = (native.addr(x) for x in (self.bufs.frame_in, self._frame_offsets,
                                                                                     self._prev))
        # The SSI decision reads ring-buffer slot s's costs: (base address, bytes per slot).
        self._cost_addr = (native.addr(b.cost), b.cost.strides[0])
        self._emit_world = np.zeros((NUM_JOINTS, 3, 3))
        # The same call fills the plausibility scorer's autoencoder input when the default criterion is there.
        ae = p.scorer.buffers() if any(isinstance(c, Plausibility) and c.scorer is p.scorer
                                       for c in p.criteria.criteria) else None
        self.ae_ready = p.scorer if ae else None
        # The default criteria, judged in one call (judge): the plausibility score on the buffers filled
        # above, and the physical criterion when the manifest's selection has one.
        crit = p.criteria.criteria
        if (ae and 1 <= len(crit) <= 2 and type(crit[0]) is Plausibility and crit[0].scorer is p.scorer
                and (len(crit) == 1 or (type(crit[1]) is PhysicalPlausibility and crit[1].params is not None))):
            sc = p.scorer
            self._physical_cost = np.zeros(N)
            self._selection = native.Selection(
                ae_out=native.addr(p.autoencoder.out), ae_rot_dim=p.autoencoder.out.shape[1],
                leg_rows=native.addr(sc._leg_rows), legs=native.addr(sc._legs), leg_err=native.addr(sc._err),
                physical=ctypes.addressof(crit[1].params) if len(crit) > 1 else None,
                physical_cost=native.addr(self._physical_cost), pos=a["pos"], ring_cost=native.addr(b.cost),
                cost_stride=b.cost.shape[1])
            self.fused_criteria = list(crit)
        f, out = p.feet, p.out
        ring = {f"ring_{k}": native.addr(getattr(b, v)) for k, v in (
            ("waist", "waist_m"), ("anchor", "anchor"), ("wrists", "wrists"), ("hand", "hand_m"), ("head", "head_m"),
            ("rot6d", "rot6d"), ("contacts", "contacts"), ("goal", "leg_goal"), ("weight", "leg_weight"),
            ("lock_weight", "lock_weight"), ("features", "features"), ("hidden", "hidden_in"))}
        sk = native.Skeleton(J=NUM_JOINTS, head=HEAD, neck=NECK, parents=a["parents"], chains=a["chains"],
                             ankles=a["ankles"], offsets=a["offsets"], poles=a["poles"])
        locks = native.FootLocks(release_frames=f.release_frames, max_slip=f.max_slip, lock_pos=a["lock_pos"],
                                 since=a["since_release"], weight=a["weight"], locked=a["locked"], raw=a["raw"])
        ctx = native.CoreContext(
            sk=sk, locks=locks, foot_ik=int(p.foot_ik), arm_ik=int(p.arm_ik), goals=a["targets"], weights=a["weights"],
            ring_rows=N + 1, hidden=b.hidden_in.shape[2], **ring,
            out_local=native.addr(out.rotations), out_world=native.addr(self._emit_world),
            out_pos=native.addr(out.positions), out_contacts=native.addr(out.contacts),
            frame_in=a["frame_in"], frame_offsets=a["frame_offsets"], prev=a["prev"], fps=p.fps,
            n_features=p.n_features, imus=p.imus, floor_lift=a["floor_lift"],
            ring_seg_m=native.addr(b.seg_m), ring_seg_flag=native.addr(b.seg_flag), imu_joints=a["imu_joints"],
            segments=int(p.segments), good_in=native.addr(self.bufs.good_in), frame_len=len(self.bufs.frame_in),
            position_limit=POSITION_LIMIT_M, latents=chk(p.latents, np.float32, (N, None), "latents"),
            latent_dim=p.latents.shape[1], target_row=-1, target_joint=native.addr(self.bufs.target_joint),
            target_goal=native.addr(self.bufs.target_goal), target_weight=native.addr(self.bufs.target_weight),
            **(dict(zip(("ae_in", "ae_local", "ae_root_local"), ae, strict=True)) if ae else {}))
        self.core = ctypes.pointer(ctx)
        self.bind_decoder(p.decoder)
        # forward_rows' arguments (the refiner's FK), filled per call.
        self._fin, self._rows_out = native.ForwardInputs(), native.PoseRows()
        self._ring_addr = {k: (native.addr(getattr(b, v)), getattr(b, v).strides[0]) for k, v in (   # (address, bytes a slot)
            ("waist", "waist_m"), ("anchor", "anchor"), ("seg_m", "seg_m"), ("seg_flag", "seg_flag"))}

    def reset(self):
        self.first = True           # the first frame's velocity is zero: prev = points

    def bind_decoder(self, dec):
        ctx, chk = self.core.contents, native.checked_addr
        self.addr["rot6d"] = chk(dec.rot6d, np.float32, (None, None), "decoder rot6d")
        self.addr["contacts"] = chk(dec.contacts, np.float32, (None, 2), "decoder contacts")
        ctx.rot6d, ctx.contacts, ctx.rot6d_stride = self.addr["rot6d"], self.addr["contacts"], dec.rot6d.shape[1]
        ctx.dec_features = chk(dec.features, np.float32, (None, self.p.n_features), "decoder features")
        ctx.dec_rows = dec.capacity
        ctx.dec_latent = chk(dec.latent, np.float32, (None, self.p.latents.shape[1]), "decoder latent")
        self._hidden_addr = [chk(h, np.float32, (None, None), "decoder GRU state") for h in dec.hidden]

    def inputs(self, sig, s, N, blend):
        """ep_frame_inputs: NumpyFrame.inputs on the frame's signals already in the pipeline's _frame_in."""
        state = self._hidden_addr[self.p.decoder._cur]
        if blend is None:
            ok = self.lib.ep_frame_inputs(self.core, s, self.first, N, -1, -1, 0.0, state)
        else:
            ok = self.lib.ep_frame_inputs(self.core, s, self.first, N, blend[0], blend[1], blend[2], state)
        if ok:
            self.first = False
        return ok == 1

    def poses(self, s, rows, N, blend, keep_world):
        """ep_frame_poses: FK, foot locks, the blend, IK and the ring copies of NumpyFrame.poses in one
        call, after its finite test of the decoder's rows (False: not finite, nothing done)."""
        dec = self.p.decoder
        c, n, a = blend if blend is not None else (0, 0, 0.0)
        return self.lib.ep_frame_poses(self.core, s, rows, N, c, n, a, self.addr["world"] if keep_world else None,
                                       self.addr["pos"], self._hidden_addr[1 - dec._cur],
                                       self._hidden_addr[dec._cur], dec.rows) == 1

    def set_target_row(self, row):
        self.core.contents.target_row = row

    def forward_rows(self, s, rot6d, rows, segments, out):
        """ep_forward: NumpyFrame.forward_rows in one C call."""
        fin, ring = self._fin, self._ring_addr
        fin.rot6d, fin.rot6d_stride = native.addr(rot6d), rot6d.shape[1]
        fin.root_m, fin.anchor = ring["waist"][0] + s * ring["waist"][1], ring["anchor"][0] + s * ring["anchor"][1]
        fin.seg_m = ring["seg_m"][0] + s * ring["seg_m"][1] if segments else None
        fin.seg_flag = ring["seg_flag"][0] + s * ring["seg_flag"][1] if segments else None
        loc, W, P = out
        self._rows_out.local, self._rows_out.world, self._rows_out.pos = native.addr(loc), native.addr(W), native.addr(P)
        self.lib.ep_forward(ctypes.byref(self.core.contents.sk), rows, ctypes.byref(fin), ctypes.byref(self._rows_out))

    def judge(self, s, N, c):
        """The default criteria (Plausibility, PhysicalPlausibility) on frame t's N samples into ring slot
        s, and the sample to move to from c (c < 0: not asked): the autoencoder, then ep_frame_costs,
        Pipeline._judge's Composite and switch_to in one C call."""
        p = self.p
        p.autoencoder.run()
        crit = self.fused_criteria
        w_phys = crit[1].weight if len(crit) > 1 else 0.0
        return self.lib.ep_frame_costs(self.core, self._selection, s, N, crit[0].weight, w_phys, c, p.switch_margin)

    def switch_to(self, s, c, margin):
        """ep_switch_to: edge.ssi.switch_to on ring slot s's costs."""
        c0, cs = self._cost_addr
        return self.lib.ep_switch_to(self.p.samples, c0 + s * cs, c, margin)

    def emit(self, s, row, out):
        """ep_emit: the row's pose made again into the output Pose (the core knows its arrays)."""
        self.lib.ep_emit(self.core, s, row)
