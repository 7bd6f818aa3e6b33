"""CompiledFrame: the frame the board runs, edge.frame.FramePath's stages as four C calls
(edge/native/postproc.c) around the two ONNX Runtime calls."""
import ctypes

import numpy as np

from edge import native
from edge.criteria import PhysicalPlausibility, Plausibility
from edge.frame import LIMB_CHAINS, LIMB_POLES, NECK, POSITION_LIMIT_M, FramePath
from edge.imus import IMU_JOINTS
from edge.physics import LEG_GUARD_MAX_PUSH_M, LEG_SEGMENTS
from edge.signals import EYE_OFFSET, GRIP_OFFSET
from edge.skeleton import ANKLES, HEAD, NUM_JOINTS, OFFSETS, PARENTS, PELVIS_TO_HEAD
from edge.smooth import SMOOTH_JOINTS


class CompiledFrame(FramePath):
    """The frame the board runs: four C calls (edge/native/postproc.c) around the two ONNX Runtime
    calls, each bit-identical to NumpyFrame's stages up to float rounding (tests/test_native.py).
    The addresses they use are found once here: the skeleton, the FrameBuffers, FootLock's state,
    the ring buffer, the output pose and the decoder's buffers (native.CoreContext)."""

    def __init__(self, spec, state, bufs, lib):
        """spec, state, bufs: as NumpyFrame's; lib: the compiled core (edge.native.load())."""
        self.spec, self.state, self.bufs, self.lib = spec, state, bufs, lib
        N, b = spec.max_samples, state.buffer
        self._check_and_address(N, b, bufs)
        a = self.addr
        self._frame_offsets = np.concatenate([EYE_OFFSET[None], GRIP_OFFSET, (PELVIS_TO_HEAD * self.spec.body_scale)[None]])
        self._prev = np.zeros((4, 3))
        a["frame_in"], a["frame_offsets"], a["prev"] = (native.addr(x) for x in (self.bufs.frame_in, self._frame_offsets,
                                                                                     self._prev))
        # The SSI decision reads ring-buffer slot s's costs: (base address, bytes per slot).
        self._cost_addr = (native.addr(b.cost), b.cost.strides[0])
        self._emit_world = np.zeros((NUM_JOINTS, 3, 3))
        # The same call fills the plausibility scorer's autoencoder input when the default criterion is there.
        ae = self.state.scorer.buffers() if any(isinstance(c, Plausibility) and c.scorer is self.state.scorer
                                       for c in self.state.criteria.criteria) else None
        self.ae_ready = self.state.scorer if ae else None
        self._bind_fused_selection(N, b, ae)
        self.core = ctypes.pointer(self._core_context(N, b, ae))
        rc = self.state.recompute.rot6d
        self._recompute_rot6d = (native.checked_addr(rc, np.float32, (None, None), "recompute rot6d"), rc.shape[1])
        # forward_rows' arguments (the refiner's FK), filled per call.
        self._fin, self._rows_out = native.ForwardInputs(), native.PoseRows()
        self._ring_addr = {k: (native.addr(getattr(b, v)), getattr(b, v).strides[0]) for k, v in (   # (address, bytes a slot)
            ("waist", "waist_m"), ("anchor", "anchor"), ("seg_m", "seg_m"), ("seg_flag", "seg_flag"))}

    def _check_and_address(self, N, b, bufs):
        """Every array the core reads or writes, checked once (dtype, layout, shape) and addressed: the
        hot path then passes addresses only (self.addr)."""
        # Arrays the C calls read by address; held here so they live as long as the pipeline.
        self._c = {"parents": np.ascontiguousarray(PARENTS, np.int64), "offsets": OFFSETS,
                   "chains": np.ascontiguousarray(LIMB_CHAINS, np.int64), "poles": LIMB_POLES,
                   "ankles": np.ascontiguousarray(ANKLES, np.int64), "imu_joints": np.ascontiguousarray(IMU_JOINTS, np.int64),
                   "leg_segs": LEG_SEGMENTS}
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
            a[k] = chk(getattr(self.state.feet, k), dtype, (N,) + getattr(self.state.feet, k).shape[1:], k)
        for arr in vars(b).values():                    # the look-ahead ring
            if isinstance(arr, np.ndarray):
                chk(arr, arr.dtype, None, "ring buffer")

    def _bind_fused_selection(self, N, b, ae):
        """The default criteria, judged in one C call (judge), when they are the plausibility score on the
        buffers the frame call fills (ae) and, where the manifest's selection has one, the physical one."""
        a = self.addr
        crit = self.state.criteria.criteria
        if (ae and 1 <= len(crit) <= 2 and type(crit[0]) is Plausibility and crit[0].scorer is self.state.scorer
                and (len(crit) == 1 or (type(crit[1]) is PhysicalPlausibility and crit[1].params is not None))):
            leg_rows, legs, leg_err = self.state.scorer.leg_error_buffers()
            self._physical_cost = np.zeros(N)
            self._selection = native.Selection(
                ae_out=native.addr(self.state.autoencoder.out), ae_rot_dim=self.state.autoencoder.out.shape[1],
                leg_rows=leg_rows, legs=legs, leg_err=leg_err,
                physical=ctypes.addressof(crit[1].params) if len(crit) > 1 else None,
                physical_cost=native.addr(self._physical_cost), pos=a["pos"], ring_cost=native.addr(b.cost),
                cost_stride=b.cost.shape[1])
            self.fused_criteria = list(crit)

    def _core_context(self, N, b, ae):
        """native.CoreContext: every address the four C calls use, in one place (the skeleton, FootLock's
        state, the FrameBuffers, the ring, the output pose, the frame's inputs, the latents, the targets,
        the smoother and, with the default criterion, the autoencoder's input)."""
        a, chk = self.addr, native.checked_addr
        f, out = self.state.feet, self.state.out
        ring = {f"ring_{k}": native.addr(getattr(b, v)) for k, v in (
            ("waist", "waist_m"), ("anchor", "anchor"), ("wrists", "wrists"), ("hand", "hand_m"), ("head", "head_m"),
            ("rot6d", "rot6d"), ("contacts", "contacts"), ("goal", "leg_goal"), ("weight", "leg_weight"),
            ("lock_weight", "lock_weight"), ("features", "features"), ("hidden", "hidden_in"))}
        sk = native.Skeleton(J=NUM_JOINTS, head=HEAD, neck=NECK, parents=a["parents"], chains=a["chains"],
                             ankles=a["ankles"], offsets=a["offsets"], poles=a["poles"])
        locks = native.FootLocks(release_frames=f.release_frames, max_slip=f.max_slip, lock_pos=a["lock_pos"],
                                 since=a["since_release"], weight=a["weight"], locked=a["locked"], raw=a["raw"],
                                 min_gap=f.min_gap, leg_guard=f.leg_guard, leg_guard_max=LEG_GUARD_MAX_PUSH_M,
                                 leg_segs=a["leg_segs"])
        return native.CoreContext(
            sk=sk, locks=locks, foot_ik=int(self.spec.foot_ik), arm_ik=int(self.spec.arm_ik), goals=a["targets"], weights=a["weights"],
            ring_rows=N + 1, hidden=b.hidden_in.shape[2], **ring,
            out_local=native.addr(out.rotations), out_world=native.addr(self._emit_world),
            out_pos=native.addr(out.positions), out_contacts=native.addr(out.contacts),
            frame_in=a["frame_in"], frame_offsets=a["frame_offsets"], prev=a["prev"], fps=self.spec.fps,
            n_features=self.spec.n_features, imus=self.spec.imus, floor_lift=a["floor_lift"],
            ring_seg_m=native.addr(b.seg_m), ring_seg_flag=native.addr(b.seg_flag), imu_joints=a["imu_joints"],
            segments=int(self.spec.segments), good_in=native.addr(self.bufs.good_in), frame_len=len(self.bufs.frame_in),
            position_limit=POSITION_LIMIT_M, latents=chk(self.state.latents, np.float32, (N, None), "latents"),
            latent_dim=self.state.latents.shape[1], target_row=-1, target_joint=native.addr(self.bufs.target_joint),
            target_goal=native.addr(self.bufs.target_goal), target_weight=native.addr(self.bufs.target_weight),
            swivel=self.spec.elbow_from_hand if self.spec.arm_ik else 0.0,
            keep_shown=int(self.spec.lookahead == 0), shown_slot=-1, shown_row=-1,    # present-frame output: see ring_changed
            **self._smoother_fields(self.state.smoother),
            **(dict(zip(("ae_in", "ae_local", "ae_root_local"), ae, strict=True)) if ae else {}))

    def _smoother_fields(self, sm):
        """The core_context fields of edge.smooth.UpperBodySmoother (none when it is off)."""
        if not sm.enabled:
            return {}
        chk, rows, slots = native.checked_addr, self.spec.max_samples + 1, self.state.buffer.slots    # the C core's ring_rows
        return dict(smooth_prev=chk(sm.prev, np.float64, (rows, SMOOTH_JOINTS, 6), "smoother state"),
                    smooth_speed=chk(sm.speed, np.float64, (rows, SMOOTH_JOINTS), "smoother speed"),
                    smooth_before=chk(sm.before, np.float64, (slots, rows, SMOOTH_JOINTS, 6), "smoother slots"),
                    smooth_before_speed=chk(sm.before_speed, np.float64, (slots, rows, SMOOTH_JOINTS),
                                            "smoother slots' speed"),
                    smooth_keep=chk(sm.keep, np.float64, (SMOOTH_JOINTS,), "smoother pass-through"),
                    smooth_min_cut=sm.min_cutoff, smooth_beta=sm.beta, smooth_speed_weight=sm.speed_weight)

    def reset(self):
        self.first = True           # the first frame's velocity is zero: prev = points
        self.ring_changed()

    def smooth_recomputed(self, k, first):
        """ep_smooth_rows: NumpyFrame.smooth_recomputed on row k of the recompute's 6D output."""
        rot, stride = self._recompute_rot6d
        self.lib.ep_smooth_rows(self.core, rot + k * stride * 4, stride, 1, first)

    def bind_decoder(self, dec):
        self.decoder = dec
        ctx, chk = self.core.contents, native.checked_addr
        self.addr["rot6d"] = chk(dec.rot6d, np.float32, (None, None), "decoder rot6d")
        self.addr["contacts"] = chk(dec.contacts, np.float32, (None, 2), "decoder contacts")
        ctx.rot6d, ctx.contacts, ctx.rot6d_stride = self.addr["rot6d"], self.addr["contacts"], dec.rot6d.shape[1]
        ctx.dec_features = chk(dec.features, np.float32, (None, self.spec.n_features), "decoder features")
        ctx.dec_rows = dec.capacity
        ctx.dec_latent = chk(dec.latent, np.float32, (None, self.state.latents.shape[1]), "decoder latent")
        self._hidden_addr = [chk(h, np.float32, (None, None), "decoder GRU state") for h in dec.hidden]

    def inputs(self, sig, s, N, blend):
        """ep_frame_inputs: NumpyFrame.inputs on the frame's signals already in FrameBuffers.frame_in."""
        state = self._hidden_addr[self.decoder.current]
        if blend is None:
            ok = self.lib.ep_frame_inputs(self.core, s, self.first, N, -1, -1, 0.0, state)
        else:
            ok = self.lib.ep_frame_inputs(self.core, s, self.first, N, blend[0], blend[1], blend[2], state)
        if ok:
            self.first = False
        return ok == 1

    def poses(self, s, rows, N, blend, keep_world, shown):
        """ep_frame_poses: FK, foot locks, the blend, IK and the ring copies of NumpyFrame.poses in one
        call, after its finite test of the decoder's rows (False: not finite, nothing done). At look-ahead
        0 the row this frame shows (the move's, or the shown sample's) goes to the output pose as well,
        so emit() has nothing to make again."""
        dec = self.decoder
        c, n, a = blend if blend is not None else (shown, 0, 0.0)
        return self.lib.ep_frame_poses(self.core, s, rows, N, c, n, a, self.addr["world"] if keep_world else None,
                                       self.addr["pos"], self._hidden_addr[dec.last_read],
                                       self._hidden_addr[dec.current], dec.rows) == 1

    def set_target_row(self, row):
        self.core.contents.target_row = row

    def ring_changed(self):
        """A move's recompute or a change of N rewrote rows of the ring: the pose ep_frame_poses left for
        emit() may be stale, so emit() makes it again."""
        self.core.contents.shown_row = -1

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

    def judge(self, s, N, c, margin):
        """The default criteria (Plausibility, PhysicalPlausibility) on frame t's N samples into ring slot
        s, and the sample to move to from c (c < 0: not asked): the autoencoder, then ep_frame_costs,
        Pipeline._judge's Composite and switch_to in one C call."""
        self.state.autoencoder.run()
        crit = self.fused_criteria
        w_phys = crit[1].weight if len(crit) > 1 else 0.0
        return self.lib.ep_frame_costs(self.core, self._selection, s, N, crit[0].weight, w_phys, c, margin)

    def switch_to(self, s, N, c, margin):
        """ep_switch_to: edge.ssi.switch_to on ring slot s's N costs."""
        c0, cs = self._cost_addr
        return self.lib.ep_switch_to(N, c0 + s * cs, c, margin)

    def emit(self, s, row, out):
        """ep_emit: the row's pose into the output Pose (the core knows its arrays): made again from the
        ring, unless ep_frame_poses left it there this frame."""
        self.lib.ep_emit(self.core, s, row)
