"""NumpyFrame: the numpy reference of a frame's stages (edge.frame.FramePath), what the compiled core
(edge.frame_compiled) is tested against bit for bit up to float rounding, and what runs without a C
compiler."""
import numpy as np

from edge import quat
from edge.features import body_points, features, heading, imu_features, orientation_features
from edge.frame import (LIMB_CHAINS, LIMB_POLES, NECK, POSITION_LIMIT_M, FramePath, fk_with_segments,
                        supported_contacts, torso_segments)
from edge.ik import apply_limb_ik, guard_legs, shoulders_out_of_torso, shoulders_to_reach, swivel_to_hands
from edge.imus import IMU_JOINTS
from edge.physics import floor_lift
from edge.skeleton import ANKLES, HEAD, NUM_PREDICTED, OFFSETS, PARENTS, TOES, fk
from edge.ssi import switch_to


class NumpyFrame(FramePath):
    """The numpy reference of a frame's stages: what the compiled core is tested against, and what
    runs without a C compiler. It works in the pipeline's FrameBuffers and ring buffer; it reads the
    decoder and a foot target's row from the pipeline each frame (bind_decoder, set_target_row: the
    FramePath defaults)."""

    def __init__(self, spec, state, bufs):
        """spec: the settings it reads (edge.frame.FrameSpec); state: the memory it works in, owned by
        the pipeline's parts (FrameState); bufs: the frame's scratch (FrameBuffers)."""
        self.spec, self.state, self.bufs = spec, state, bufs
        self._recompute_rows = self.state.smoother.recompute_views(self.state.recompute.rot6d)     # smooth_recomputed's rows

    def reset(self):
        self.prev_points = None     # the previous frame's body points (velocity features)

    def sane(self):
        v, head, hands = self.bufs.frame_in, self.bufs.inputs["head_pos"], self.bufs.inputs["hand_pos"]
        total = float(v.sum())
        return (total - total == 0.0 and -POSITION_LIMIT_M < head.min() and head.max() < POSITION_LIMIT_M
                and -POSITION_LIMIT_M < hands.min() and hands.max() < POSITION_LIMIT_M)

    def inputs(self, sig, s, N, blend):
        """Body points, features and tracker matrices of one frame into ring slot s and the decoder, and
        the spare row N's latent and GRU state eased between a live move's two samples (blend: from,
        to, weight; or None). False, doing nothing, when the frame is not sane (the pipeline's
        FrameBuffers.frame_in); a frame that is is kept in good_in."""
        b, dec = self.state.buffer, self.decoder
        if not self.sane():
            return False
        np.copyto(self.bufs.good_in, self.bufs.frame_in)
        if blend is not None:
            c, n, a = blend
            a = np.float64(a)       # eased in float64, rounded once to the decoder's float32 (as ep_frame_inputs)
            dec.latent[N] = (1 - a) * self.state.latents[c] + a * self.state.latents[n]
            dec.state[N] = (1 - a) * dec.state[c] + a * dec.state[n]
        points, waist_rot = body_points(sig, self.spec.body_scale)
        points, waist_rot = points[0], waist_rot[0]
        prev = points if self.prev_points is None else self.prev_points
        self.prev_points = points
        yaw_q = heading(waist_rot)
        feat = features(points, prev, yaw_q, self.spec.fps)
        if self.spec.imus:
            feat = np.concatenate([feat, imu_features(sig.imu_rot[0], sig.imu_flag[0], yaw_q)])
        if self.spec.orientations:
            feat = np.concatenate([feat, orientation_features(sig.head_rot[0], sig.hand_rot[0], yaw_q)])
        q = self.bufs.quats                         # waist, hands, head: one to_matrix call
        q[0], q[1:3], q[3] = waist_rot, sig.hand_rot[0], sig.head_rot[0]
        m = quat.to_matrix(q)
        b.features[s] = feat
        b.anchor[s] = points[0]
        b.wrists[s] = points[1:3]
        b.waist_m[s], b.hand_m[s], b.head_m[s] = m[0], m[1:3], m[3]
        if self.spec.segments:
            b.seg_m[s, IMU_JOINTS] = quat.to_matrix(sig.imu_rot[0])
            b.seg_flag[s, IMU_JOINTS] = sig.imu_flag[0]
            torso_segments(b.seg_m[s], b.seg_flag[s], m[0], m[3])
        dec.features[:] = feat
        b.hidden_in[s, :N] = dec.state[:N]
        return True

    def finite(self, dec):
        return bool(np.isfinite(dec.state[:dec.rows]).all() and np.isfinite(dec.rot6d[:dec.rows]).all())

    def poses(self, s, rows, N, blend, keep_world, shown):
        """Every row's pose of frame s: FK, foot locks, the transition row's blended goals, IK; and
        what the ring keeps of them. False, doing nothing, when a decoder row is not finite."""
        b, dec = self.state.buffer, self.decoder
        if not self.finite(dec):
            return False
        self.state.smoother.remember(s, N)              # the upper body's one-euro filter (edge.smooth), in place
        self.state.smoother.apply(dec.rot6d, rows)
        self.forward(dec.rot6d[:rows], b.waist_m[s], b.anchor[s], b.seg_m[s], b.seg_flag[s])
        if self.spec.foot_ik:
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
        b.lock_weight[s, :N] = self.state.feet.weight[:N]
        return True

    def smooth_recomputed(self, k, first):
        """The upper body's filter (edge.smooth) on row k of a move's recompute, with state row `first`."""
        self.state.smoother.apply_to(self._recompute_rows[k], 1, first)

    def switch_to(self, s, N, c, margin):
        return switch_to(self.state.buffer.cost[s, :N], c, margin)

    def emit(self, s, row, out):
        self.row_pose(s, row, out.positions, out.rotations)
        out.contacts[:] = supported_contacts(self.state.buffer.contacts[s, row], out.positions)

    def row_pose(self, s, row, positions, rotations):
        """The pose of one row of ring slot s, made again from what the ring keeps."""
        b = self.state.buffer
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
        b = self.state.buffer
        seg = (b.seg_m[s], b.seg_flag[s]) if segments else (None, None)
        self.forward(rot6d[:rows], b.waist_m[s], b.anchor[s], *seg, out=out)

    def foot_goals(self, N):
        """Update the N samples' foot-contact locks from the decoder's contacts and the FK ankles; each
        sample's foot goal (in _targets) is where its lock draws the ankle, so the leg IK runs at weight 1.
        Returns (goals [N,2,3], lock weights [N,2])."""
        goal, pos = self.bufs.targets[:N], self.bufs.pos
        toe_drop = (self.bufs.world[:N, ANKLES] @ self.bufs.toe_offsets)[..., 1, 0]   # for the locks' floor snap
        lock, w = self.state.feet.update(self.decoder.contacts[:N], pos[:N, ANKLES], toe_drop)
        ankle = pos[:N, ANKLES]
        np.subtract(lock, ankle, out=goal)
        goal *= w[..., None]
        goal += ankle
        self.bufs.weights[:N] = 1.0
        if self.state.feet.leg_guard > 0:
            guard_legs(pos, goal, w, self.state.feet.leg_guard)
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
        if not (self.spec.foot_ik or self.spec.arm_ik):
            return
        loc, W, P = self.bufs.local[:rows], self.bufs.world[:rows], self.bufs.pos[:rows]
        tgt, wts, ends = self.bufs.limb_targets[:rows], self.bufs.limb_weights[:rows], self.bufs.limb_ends[:rows]
        tgt[:, :2] = self.bufs.targets[:rows]
        tgt[:, 2:] = wrists
        wts[:, :2] = self.bufs.weights[:rows] if self.spec.foot_ik else 0.0
        if self.spec.foot_ik:               # the effective leg goals, lifted clear of the floor, at weight 1
            ankle = P[:, ANKLES]
            tgt[:, :2] = ankle + wts[:, :2, None] * (tgt[:, :2] - ankle)
            lift = floor_lift(tgt[:, :2, 1], (W[:, ANKLES] @ self.bufs.toe_offsets)[..., 1, 0])
            tgt[:, :2, 1] += lift
            wts[:, :2] = 1.0
            self.bufs.floor_lift[:rows] = lift
        ends[:, :2] = W[:, ANKLES]
        ends[:, 2:] = hand_m if self.spec.arm_ik else W[:, LIMB_CHAINS[2:, 2]]
        if self.spec.arm_ik:
            shoulders_to_reach(loc, W, P, PARENTS, LIMB_CHAINS[2:], OFFSETS, wrists)
        apply_limb_ik(loc, W, P, PARENTS, LIMB_CHAINS, tgt, wts, LIMB_POLES, ends, OFFSETS)
        P[:, TOES] = P[:, ANKLES] + (W[:, ANKLES] @ self.bufs.toe_offsets)[..., 0]
        if self.spec.arm_ik and self.spec.elbow_from_hand > 0:
            swivel_to_hands(loc, W, P, PARENTS, LIMB_CHAINS[2:], OFFSETS, self.spec.elbow_from_hand)
            shoulders_out_of_torso(loc, W, P, PARENTS, LIMB_CHAINS[2:])
        if self.spec.arm_ik:
            W[:, HEAD] = head_m
            loc[:, HEAD] = np.swapaxes(W[:, NECK], -1, -2) @ head_m
