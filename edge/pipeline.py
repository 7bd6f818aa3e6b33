"""The one per-frame path from tracker signals to a full-body pose, with SSI.

`edge eval`, `edge run` and `edge replay` drive this object; they differ only in where frames come
from and where poses go. Per frame t:

  body points -> features -> decoder (N samples + a transition row, one batched call)
  -> FK hung from the tracked head -> foot-contact locks and leg IK, arm IK -> FK
  -> criteria on frame t (plausibility, targets, obstacles, extra IMUs) -> SSI decision at t
  -> output frame t - tau, its pose made again from what the look-ahead ring buffer keeps.

With the compiled core and the default criteria that is four C calls around the two ONNX Runtime
calls (ep_frame_inputs, ep_frame_poses, ep_frame_costs after the autoencoder: the costs and the SSI
test, ep_emit).

Two ways through a frame's stages (edge.frame.FramePath), chosen once, on the same FrameBuffers:
CompiledFrame (edge.frame_compiled), the fused C calls the board runs, and NumpyFrame
(edge.frame_numpy), the numpy reference they are tested against (and the fallback without a
compiler). SSI's decisions (the outlier test, the best other sample, the move's schedule, the
look-ahead ring) are edge.ssi; this file composes the stages, the decoder, the refiner and SSI.

Adaptive N: buffers are sized for `max_samples` once; `set_samples(n)` runs the first n of them
from then on (edge.governor decides n from the frame times). Dropping the shown sample reuses the
SSI transition; a revived sample starts from the shown sample's GRU state, so nothing pops.
"""
import time

import numpy as np

from edge import native, quat
from edge.criteria import Composite, FrameContext, PhysicalPlausibility, Plausibility
from edge.features import NUM_FEATURES, NUM_POINT_FEATURES
from edge.frame import FrameBuffers, FrameSpec, FrameState, Pose, RowFk, ease, ring_runs
from edge.frame_compiled import CompiledFrame
from edge.frame_numpy import NumpyFrame
from edge.imus import IMU_JOINTS, NUM_IMUS
from edge.heading import HeadingObserver
from edge.ik import FootLock
from edge.inference import Autoencoder, Decoder
from edge.loading import open_jacobian, open_models
from edge.modelfiles import ModelError
from edge.options import PipelineOptions
from edge.physics import INTERSECT_M
from edge.plausibility import PlausibilityScorer
from edge.refine import Refiner
from edge.signals import Signals
from edge.smooth import UpperBodySmoother
from edge.ssi import LookaheadBuffer, Switcher, transition_weight
from edge.skeleton import NUM_JOINTS

# The parts of a live frame, in order; with `timing` on, step() stamps the thread CPU clock after each
# (Pipeline.stage_ns[k + 1] - stage_ns[k] is stage k's time; `edge profile` reads them).
STAGES = ("features", "decoder", "poses", "criteria", "selection", "emit")


def latent_scale(selection):
    """The spread of the SSI samples' latents, as a multiple of the prior's (a manifest's or --selection's
    `latent_scale`; 1 when it has none). Anything but a number in (0, 4] is refused with the fix."""
    x = selection.get("latent_scale", 1.0)
    if isinstance(x, bool) or not isinstance(x, (int, float)) or not 0.0 < x <= 4.0:
        raise ModelError(f"selection latent_scale must be a number in (0, 4], got {x!r}: fix the model manifest's "
                         "\"selection\" (1.0 draws the samples at the prior's own spread)")
    return float(x)


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
        self.foot_ik, self.arm_ik, self.elbow_from_hand = o.foot_ik, o.arm_ik, float(o.elbow_from_hand)
        self.manifest, dec_session, ae_session = open_models(models, o.threads, o.precision)
        self._open(dec_session, ae_session, o.use_native)
        self._choose(o.selection or self.manifest.get("selection", {}), criteria, o.use_native, o.seed)
        self._allocate_ssi()
        # One state row per sample and the transition's, as the ring's rows (ring_rows in the C core).
        self.smoother = UpperBodySmoother(self.max_samples + 1, self.buffer.slots, o.fps, o.smooth_min_cutoff,
                                          o.smooth_beta)
        self.bufs = FrameBuffers(self.rows, self.lookahead, self.samples, self.imus, o.arm_ik, self.buffer)
        self.out = Pose()
        self._choose_paths(dec_session, models, o.use_native, o.threads)
        self.reset()

    def _open(self, dec_session, ae_session, use_native):
        """The decoder (N rows and a transition row), its look-ahead recompute, the autoencoder and scorer."""
        m, N, lookahead = self.manifest, self.samples, self.lookahead
        # what runs: int8 falls back to fp32 where its start-up self-check fails (edge.int8check)
        self.precision, self.precision_note = m["precision"], m["precision_note"]
        # The decoder's input: the 24 point features, the extra IMUs' 49 when the model reads them, and the
        # headset's and controllers' orientations (18) when it has an upper-body head (v0.5 on).
        self.n_features = m["features"]
        self.imus = NUM_IMUS if self.n_features > NUM_POINT_FEATURES else 0
        self.orientations = self.n_features > NUM_FEATURES
        # A worn IMU also sets its segment's world rotation after the decoder (fk_with_segments).
        self.segments = bool(self.options.segments and self.imus)
        self.rows = N + 1 if N > 1 else N   # the extra row carries a live transition
        self.decoder = Decoder(dec_session, self.rows, m["latent"], m["hidden"], m["features"], shared_features=True)
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
                                "w_hidden": np.repeat(w[..., None], H, 2), "w_goal": np.tile(w[..., None, None], (1, 1, 2, 3)),
                                "a": [float(a) for a in w[1]]}     # a as Python floats: a switch makes no scalars
        self.feet = FootLock(N, leg_guard=self.options.leg_guard)

    def _choose_paths(self, dec_session, models, use_native, threads):
        """The compiled core or the numpy reference, and the heading observer and refiner if asked."""
        m, fps, o = self.manifest, self.fps, self.options
        # The compiled core (edge/native) runs the whole frame around the two ONNX calls when a C
        # compiler is there; NumpyFrame is the reference and the fallback.
        self.native = native.load() if use_native else None
        spec = FrameSpec(self.fps, self.body_scale, self.foot_ik, self.arm_ik, self.elbow_from_hand, self.imus,
                         self.orientations, self.segments, self.n_features, self.lookahead, self.max_samples)
        state = FrameState(self.buffer, self.latents, self.feet, self.smoother, self.recompute, self.out,
                           self.autoencoder, self.scorer, self.criteria)
        self.reference = NumpyFrame(spec, state, self.bufs)
        self.path = CompiledFrame(spec, state, self.bufs, self.native) if self.native else self.reference
        self.decoder = self._decoder                    # bound to both paths
        self.timing, self.stage_ns = False, np.zeros(len(STAGES) + 1, np.int64)
        # The extra IMUs' heading observer (edge.heading), on when IMUs are worn and options.heading is set.
        self.heading = (HeadingObserver(fps, o.heading, decoder_fk=RowFk(self.path, self.buffer.rot6d))
                        if o.heading is not None and self.imus else None)
        # Latent refinement of the shown sample (edge.refine), when options.refine is set.
        self.refiner = None
        if o.refine is not None:
            compiled = (self.native, self.path.core) if self.native else None
            self.refiner = Refiner(dec_session, m, self.path.forward_rows, o.refine, fps, compiled=compiled,
                                   jacobian_session=open_jacobian(models, threads, self.precision))
        self._legs = self.refiner.term("legs") if self.refiner is not None else None     # LegsApart, armed each frame
        if self._legs is not None:
            self._legs.watch(self.bufs.pos)

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
            self.reference.bind_decoder(dec)
            if self.path is not self.reference:
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
        if self.refiner is not None:
            self.refiner.reset()
        self.feet.reset()
        self.smoother.reset()
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
        """Feed one frame of Signals (T=1). Returns the Pose for frame t - tau, or None while the buffer fills.
        The stages, in order, each stamped in stage_ns when timing: inputs, decode (and refine), poses,
        judge, decide, emit."""
        timing, mark = self.timing, self.stage_ns
        if timing:
            mark[0] = time.thread_time_ns()
        self.t += 1
        t, b, N, sw = self.t, self.buffer, self.samples, self.switcher
        s = t % b.slots
        b.frame[s] = t
        b.override[s] = False
        sig, live, blend = self._inputs(sig, s, N)
        if timing:
            mark[1] = time.thread_time_ns()
        self.decoder.step()
        if self.refiner is not None:
            self._refine(s, N, sw.current)
        if timing:
            mark[2] = time.thread_time_ns()
        fused, keep_world = self._poses(s, N, live, blend)
        if timing:
            mark[3] = time.thread_time_ns()
        n, ask = self._judge_frame(sig, s, N, fused, keep_world)
        if timing:
            mark[4] = time.thread_time_ns()
        self._decide(n, ask, t, s)
        if timing:
            mark[5] = time.thread_time_ns()
        pose = self._emit(t - self.lookahead)
        if timing:
            mark[6] = time.thread_time_ns()
        return pose

    def _inputs(self, sig, s, N):
        """The frame's signals into slot s and the decoder: (the Signals used, whether a move is live, its
        blend). The extra IMUs' headings are corrected before anything reads them (edge.heading); during
        a move the spare row carries it, both latents and GRU states eased (path.inputs does it)."""
        sw = self.switcher
        self._load_frame_in(sig)
        if self.heading is not None:
            sig = self.heading.correct_frame(self.bufs.inputs, sig)
        live = sw.live(self.t)
        blend = (sw.trans[0], sw.trans[1], sw.weight(self.t)) if live else None
        # Features and tracker matrices into slot s and the decoder, if the frame is sane: finite, and
        # inside POSITION_LIMIT_M of the origin (no play space is larger). One that a range check upstream
        # did not catch is replaced by the last good one.
        if not self.path.inputs(sig, s, N, blend):
            sig = self._held_frame()
            self.path.inputs(sig, s, N, blend)
        return sig, live, blend

    def _poses(self, s, N, live, blend):
        """Post-processing for every row at once: (whether the default criteria are judged in one C call,
        whether a criterion needs every joint's world rotation). The transition row (row N) blends the two
        samples' foot goals (not lock positions, which are stale for a foot that is free) and, like the
        samples, runs the leg IK at weight 1: the goals already carry each lock's pull, so the row's first
        and last frames are the two samples' own poses."""
        dec, b, sw = self.decoder, self.buffer, self.switcher
        fused = self.criteria.criteria == self.path.fused_criteria     # the default criteria: judged in one C call
        keep_world = not fused and self.criteria.needs_world_rot  # every joint's world rotation, only if a criterion asks
        rows = N + 1 if live else N
        sm = self.smoother
        if sm.enabled:                  # the upper body's filter (edge.smooth), run inside path.poses
            if sm.fresh and np.isfinite(dec.rot6d[:dec.rows]).all():     # a clip's first frame
                sm.prime(dec.rot6d, dec.rows)
            if live:
                sm.blend_into(blend[0], blend[1], blend[2], N)
        if not self.path.poses(s, rows, N, blend, keep_world, sw.current):   # a decoder row went non-finite
            self._heal(dec, s)
            self.path.poses(s, rows, N, blend, keep_world, sw.current)
        if live:
            b.override[s] = True
            b.trans_row[s] = N
        if self._legs is not None:      # the legs' clearance for the next frame, from the pose shown now
            self._legs.arm(N if live else sw.current, self.feet.weight[sw.current])
        if self.heading is not None:    # each IMU against its reference (edge.heading), at the observer's rate
            self.heading.observe_frame(self.t, self.bufs.inputs, s, sw.current)
        return fused, keep_world

    def _judge_frame(self, sig, s, N, fused, keep_world):
        """Judge frame t, the newest (3.2.4: detection at t + tau relative to the output): (the sample to
        move to, -1 for none; whether a move could start). A new switch waits until the last transition
        has been sent, so transitions never overlap; refinement owns the shown sample while it holds."""
        sw = self.switcher
        ask = (self._pending is None and self.ssi and N > 1 and sw.free(self.t)
               and not (self.refiner is not None and self.refiner.holds(self.t)))
        n = -1
        if N > 1:
            c = sw.current if ask else -1
            n = self.path.judge(s, N, c, self.switch_margin) if fused else self._judge(sig, s, N, c, keep_world)
        return n, ask

    def _decide(self, n, ask, t, s):
        """Home to sample 0 when nothing better was found, apply a change of N, or start the move to n."""
        sw = self.switcher
        if n < 0 and ask and self.home_after and sw.current != 0:
            n = self._homeward(s, sw.current)
        if self._pending is not None:
            self._apply_samples(t, s)
        elif n >= 0:
            self._start_transition(n, t)

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
        out = self.refiner.refine(self.t, dec.latent[c], self.latents[c], dec.hidden[dec.last_read][c], dec.features[0],
                                  self.buffer.seg_m[s], self.buffer.seg_flag[s], f.lock_pos[c], f.weight[c], row=c,
                                  slot=s)
        if out is not None:
            dec.rot6d[c], dec.contacts[c], dec.state[c] = out
        pulls = self.refiner.foot_pull(self.t, self.bufs.target_joint, self.bufs.target_goal, self.bufs.target_weight)
        self._set_target_row(c if pulls else -1)

    def _set_target_row(self, row):
        """The row whose leg goals a foot target pulls this frame (-1: none), for both paths' foot goals."""
        if row != self.bufs.target_row[0]:
            self.bufs.target_row[0] = row
            self.path.set_target_row(row)

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
        return self.path.switch_to(s, N, c, self.switch_margin) if c >= 0 else -1

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
            self.smoother.set_row(r, dec.rot6d[r])
        if self.smoother.fresh and self.smoother.enabled:
            self.smoother.prime(dec.rot6d, R)
        if not np.isfinite(dec.features).all():     # the ring must not keep what a recompute would re-run
            self.buffer.features[s] = self.buffer.features[prev] if held else 0.0
        self.state_resets += int(bad.sum())

    def _load_frame_in(self, sig):
        """One frame (T=1) of Signals into FrameBuffers.frame_in, the C calls' input layout (no temporaries)."""
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
        transition to one of them can be recomputed over the look-ahead like any other.

        A running move's buffered frames keep their spare row at the old N (lo), which becomes a sample
        here: it moves to the new spare row (hi) first, or those frames would show the sample the move
        leaves (a pop of 2 cm on the bundled walk)."""
        c, b, dec = self.switcher.current, self.buffer, self.decoder
        self.path.ring_changed()
        moving = b.override & (b.trans_row == lo)
        if moving.any():
            for a in (b.rot6d, b.contacts, b.leg_goal, b.leg_weight):
                a[moving, hi] = a[moving, lo]
            b.trans_row[moving] = hi
        dec.latent[lo:hi] = self.latents[lo:hi]
        dec.state[lo:hi] = dec.state[c]
        self.feet.copy_rows(c, slice(lo, hi))
        self.smoother.copy_rows(c, slice(lo, hi))
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
        self.path.ring_changed()
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
        sm = self.smoother
        if sm.enabled:                  # each frame's smoothing from its blend of c's and n's states then
            for k in range(K):
                sm.blend_into(c, n, sc["a"][k], N, slot=(s0 + k) % b.slots)
                self.path.smooth_recomputed(k, N)
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


