"""Training windows made where the model is: motion.dataset.make_batch in torch, on the accelerator.

v0.4's run waited for numpy batch makers a third of the time. Here the training split lives on the
device (the pack, expanded to 60 Hz: about 0.4 GB of float32 for data v4) and each batch is drawn and
rendered there in a few dozen batched kernels: window picks, the random heading and floor shift, FK,
the headset and controllers with their device noise, the waist puck, the extra IMUs with their noise,
which ones are worn and when each is heard (DragPoser's sets and faults, with the synchroniser's hold
and fade), the features the board computes (edge.features), and the targets.

The numpy path (motion.dataset.draw_batch / render_batch) stays the reference: `render` here takes the
same dict of random numbers that draw_batch makes, so tests/test_batches.py renders one draw both ways
and compares every output; `draw` makes the same distributions with torch's generator.

    batches = DeviceBatches(cs_train, window=60, device="cuda", seed=1)
    b = batches.next(256)        # dict of tensors on the device, the keys and shapes of make_batch's
"""
import numpy as np
import torch

from edge.features import NUM_POINT_FEATURES
from edge.imus import COMMON_SETS, FADE_S, LOST_AFTER_S, IMU_JOINTS, NUM_IMUS, ImuNoise, mask
from edge.signals import EYE_OFFSET, GRIP_OFFSET
from edge.skeleton import HEAD, JOINT, LEVELS, OFFSETS, PARENTS, PELVIS_TO_HEAD, PREDICTED
from motion.augment import MIRROR_IMUS, MIRROR_JOINTS, Augment, window_span
from motion.dataset import FPS, ClipSet, WindowDraw, vigorous_starts, window_starts
from motion.synth import DeviceNoise

WRISTS = [JOINT["l_wrist"], JOINT["r_wrist"]]


# ---------------------------------------------------------------- quaternions (edge.quat, in torch)

def qmul(a, b):
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                        aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw], dim=-1)


def qinv(q):
    return q * q.new_tensor([1.0, -1.0, -1.0, -1.0])


def qrot(q, v):
    """Rotate vectors v [...,3] by unit quaternions q [...,4]."""
    u = q[..., 1:]
    t = 2.0 * torch.linalg.cross(u, v)
    return v + q[..., :1] * t + torch.linalg.cross(u, t)


def qnormalize(q):
    return q / q.norm(dim=-1, keepdim=True).clamp_min(1e-8)


def qslerp(a, b, t):
    """edge.quat.slerp: from a towards b by t [...] (the shorter way)."""
    t = t[..., None]
    d = (a * b).sum(-1, keepdim=True)
    b = torch.where(d < 0, -b, b)
    theta = torch.arccos(d.abs().clamp(-1.0, 1.0))
    s = torch.sin(theta)
    near = s < 1e-6
    safe = torch.where(near, torch.ones_like(s), s)
    wa = torch.where(near, 1.0 - t, torch.sin((1.0 - t) * theta) / safe)
    wb = torch.where(near, t, torch.sin(t * theta) / safe)
    return qnormalize(wa * a + wb * b)


def qto_matrix(q):
    w, x, y, z = q.unbind(-1)
    return torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], dim=-1
                       ).reshape(q.shape[:-1] + (3, 3))


def from_axis_angle(axis, angle):
    """Axes [...,3] (any length) and angles in radians [...] -> quaternions [...,4]."""
    axis = axis / axis.norm(dim=-1, keepdim=True)
    half = angle[..., None] / 2
    return torch.cat([torch.cos(half), torch.sin(half) * axis], dim=-1)


def from_yaw(theta):
    up = theta.new_tensor([0.0, 1.0, 0.0]).expand(theta.shape + (3,))
    return from_axis_angle(up, theta)


def yaw_of(q):
    """Heading about +Y of the frame's forward axis (+Z), radians (edge.quat.yaw)."""
    fwd = qrot(q, q.new_tensor([0.0, 0.0, 1.0]).expand(q.shape[:-1] + (3,)))
    return torch.atan2(fwd[..., 0], fwd[..., 2])


def matrix_to_6d(m):
    return torch.cat([m[..., :, 0], m[..., :, 1]], dim=-1)


# ---------------------------------------------------------------- the batch, from its random numbers

def world_quats(rot, root, offsets):
    """FK with quaternions: local rotations [...,J,4], root [...,3] -> (world rotations [...,J,4],
    positions [...,J,3]); edge.skeleton.fk's levels, one batched step per depth."""
    J = rot.shape[-2]
    wq = [None] * J
    wp = [None] * J
    wq[0], wp[0] = rot[..., 0, :], root
    for idx in LEVELS:
        for j in idx:
            p = PARENTS[j]
            wq[j] = qmul(wq[p], rot[..., j, :])
            wp[j] = wp[p] + qrot(wq[p], offsets[j].expand_as(root))
    return torch.stack(wq, dim=-2), torch.stack(wp, dim=-2)


def smooth_noise(first, steps, a):
    """motion.synth.smooth_noise as one matmul: out[t] = a^t first + sum_{1<=s<=t} a^(t-s) sqrt(1-a^2) steps[s]."""
    T = steps.shape[0]
    t = torch.arange(T, device=steps.device, dtype=steps.dtype)
    powers = torch.tril(a ** (t[:, None] - t[None, :]).clamp_min(0))
    powers[:, 0] = 0
    w = (steps * np.sqrt(1 - a * a)).reshape(T, -1)
    return ((powers @ w).reshape(steps.shape) + (a ** t).reshape((T,) + (1,) * first.dim()) * first)


def fade(alive, held, fps, lost_after_s=LOST_AFTER_S, fade_s=FADE_S):
    """edge.imus.fade in torch: alive [T,...,K] bool, held [T,...,K,4] -> (flags, held orientations)."""
    T = alive.shape[0]
    lost_n, step = int(round(lost_after_s * fps)), 1.0 / max(1.0, fade_s * fps)
    flags = torch.empty(alive.shape, dtype=held.dtype, device=held.device)
    out = held.clone()
    flag = alive[0].to(held.dtype)
    since = torch.where(alive[0], 0, lost_n + 1)
    flags[0] = flag
    for t in range(1, T):
        a = alive[t]
        since = torch.where(a, 0, since + 1)
        target = (since < lost_n).to(held.dtype)
        flag = (flag + (target - flag).clamp(-step, step)).clamp(0.0, 1.0)
        flags[t] = flag
        out[t] = torch.where(a[..., None], held[t], out[t - 1])
    return flags, out


class DeviceBatches:
    """The training split on a device and the batches made from it there (see the module docstring)."""

    def __init__(self, cs: ClipSet, window, device="cpu", seed=0, noise=None, imu_noise=None,
                 dtype=torch.float32, flaky=1 / 3, vigorous=0.0, windows_by="frames", cap_minutes=10.0,
                 augment: Augment = None):
        self.window, self.device, self.dtype = window, torch.device(device), dtype
        self.noise = DeviceNoise() if noise is None else noise
        self.imu_noise = ImuNoise() if imu_noise is None else imu_noise
        self.flaky = flaky
        as_t = dict(device=self.device, dtype=dtype)
        self.rotations = torch.as_tensor(cs.rotations, **as_t)
        self.root = torch.as_tensor(cs.root, **as_t)
        self.contacts = torch.as_tensor(cs.contacts, device=self.device, dtype=torch.float32)
        # a window read at up to `fastest` x needs that many more frames of its clip (motion.augment)
        self.augment = augment
        starts = window_starts(cs, window_span(window, augment.fastest if augment else 1.0))
        self.starts = torch.as_tensor(starts, device=self.device)
        by_person = WindowDraw(cs, starts, windows_by, cap_minutes).cdf          # None: uniform over frames
        self.person_cdf = None if by_person is None else torch.as_tensor(by_person, device=self.device)
        self.mirror_joints = torch.as_tensor(MIRROR_JOINTS, device=self.device)
        self.mirror_imus = torch.as_tensor(MIRROR_IMUS, device=self.device)
        # --vigorous: that share of every batch from windows that lift a toe (motion.dataset.vigorous_starts)
        self.vigorous = vigorous
        self.lifted = torch.as_tensor(vigorous_starts(cs, starts, window) if vigorous > 0 else starts, device=self.device)
        self.gen = torch.Generator(self.device).manual_seed(seed)
        self.offsets = torch.as_tensor(OFFSETS, **as_t)
        self.eye = torch.as_tensor(EYE_OFFSET, **as_t)
        self.grip = torch.as_tensor(GRIP_OFFSET, **as_t)
        self.pelvis_to_head = torch.as_tensor(PELVIS_TO_HEAD, **as_t)
        self.sets = torch.as_tensor(np.array([mask(s) for s in COMMON_SETS]), **as_t)
        self.imu_joints = torch.as_tensor(IMU_JOINTS, device=self.device)
        self.predicted = torch.as_tensor(PREDICTED, device=self.device)

    def next(self, batch, with_imus=True):
        return self.render(self.draw(batch, with_imus))

    # ---- the random numbers: motion.dataset.draw_batch's, from torch's generator

    def _normal(self, *shape):
        return torch.randn(shape, generator=self.gen, device=self.device, dtype=self.dtype)

    def _uniform(self, lo, hi, *shape):
        return lo + (hi - lo) * torch.rand(shape, generator=self.gen, device=self.device, dtype=self.dtype)

    def draw(self, B, with_imus=True):
        W, K, n, dn = self.window, NUM_IMUS, self.noise, self.imu_noise
        n_lifted = int(round(self.vigorous * B))
        if self.person_cdf is None:
            pick = torch.randint(len(self.starts), (B - n_lifted,), generator=self.gen, device=self.device)
        else:
            u = torch.rand(B - n_lifted, generator=self.gen, device=self.device, dtype=torch.float64)
            pick = torch.searchsorted(self.person_cdf, u).clamp_max(len(self.starts) - 1)
        lift = torch.randint(len(self.lifted), (n_lifted,), generator=self.gen, device=self.device)
        d = {"starts": torch.cat([self.starts[pick], self.lifted[lift]]), "yaw": self._uniform(-np.pi, np.pi, B),
             "shift": torch.stack([self._uniform(-2, 2, B), torch.zeros(B, device=self.device, dtype=self.dtype),
                                   self._uniform(-2, 2, B)], dim=1)}
        d["device"] = {"wander": self._normal(W, B, 3, 3), "wander0": self._normal(B, 3, 3),
                       "jitter": self._normal(W, B, 3, 3), "rot_axis": self._normal(W, B, 4, 3),
                       "rot_deg": self._uniform(0, n.rot_max_deg, W, B, 4),
                       "yaw_offset_deg": self._normal(B) * n.yaw_offset_std_deg,
                       "yaw_drift_deg_s": self._normal(B) * n.yaw_drift_deg_s, "acc": self._normal(W, B, 3)}
        if with_imus:
            d["worn"], d["alive"] = self.random_imus(B)
            d["imu"] = {"mount_axis": self._normal(B, K, 3), "mount_deg": self._uniform(0, dn.mount_max_deg, B, K),
                        "yaw_offset_deg": self._normal(B, K) * dn.yaw_offset_std_deg,
                        "yaw_drift_deg_s": self._normal(B, K) * dn.yaw_drift_deg_s,
                        "jitter_axis": self._normal(W, B, K, 3), "jitter_deg": self._uniform(0, dn.jitter_max_deg, W, B, K)}
        a = self.augment
        if a is not None and a.mirror > 0:
            d["mirror"] = torch.rand(B, generator=self.gen, device=self.device) < a.mirror
        if a is not None and a.retimes:
            d["speed"] = torch.exp(self._uniform(np.log(a.slowest), np.log(a.fastest), B))
        return d

    def random_imus(self, B, p_drop=0.01, outage=100):
        """motion.dataset.random_imus in torch: worn [B,7], alive [W,B,7]."""
        W, K, dev = self.window, NUM_IMUS, self.device
        kind = torch.rand(B, generator=self.gen, device=dev)
        common = torch.randint(len(self.sets), (B,), generator=self.gen, device=dev)
        subset = (torch.rand(B, K, generator=self.gen, device=dev) < 0.5).to(self.dtype)
        worn = torch.where(((kind >= 0.25) & (kind < 0.6))[:, None], self.sets[common],
                           torch.where((kind >= 0.6)[:, None], subset, torch.zeros_like(subset)))
        drop = (torch.rand(B, K, generator=self.gen, device=dev) < 0.3) & (worn > 0)
        start = torch.randint(0, W, (B, K), generator=self.gen, device=dev)
        length = torch.randint(5, 46, (B, K), generator=self.gen, device=dev)
        t = torch.arange(W, device=dev)[:, None, None]
        silent = drop & (t >= start) & (t < start + length)
        protocol = (torch.rand(B, generator=self.gen, device=dev) < self.flaky)[None, :, None]
        since = torch.cumsum(torch.rand(W + outage, B, K, generator=self.gen, device=dev) < p_drop, dim=0)
        down = (since[outage:] - since[:W]) > 0
        alive = (worn[None] > 0) & ~torch.where(protocol, down, silent)
        return worn, alive

    # ---- the batch: motion.dataset.render_batch, deterministic given the numbers

    def render(self, d):
        W = self.window
        as_t = dict(device=self.device, dtype=self.dtype)
        t = lambda x: torch.as_tensor(x, **as_t)                      # noqa: E731 (numpy draws, in a test)
        rot, root, contacts = self.window_motion(d)                    # [W,B,J,4], [W,B,3], [W,B,2]
        yaw = from_yaw(t(d["yaw"]))
        rot = torch.cat([qmul(yaw[None], rot[:, :, 0])[:, :, None], rot[:, :, 1:]], dim=2)
        root = qrot(yaw[None].expand(W, -1, -1), root) + t(d["shift"])[None]
        world_rot, gt_pos = world_quats(rot, root, self.offsets)
        sig = self.signals(world_rot, gt_pos, {k: t(v) for k, v in d["device"].items()})
        imu_rot, imu_flag = world_rot[..., self.imu_joints, :], None
        if "worn" in d:
            worn, alive = t(d["worn"]), torch.as_tensor(d["alive"], device=self.device)
            if "mirror" in d:       # the IMU on the person's left foot is on the mirror image's right foot
                m = torch.as_tensor(d["mirror"], device=self.device)
                worn = torch.where(m[:, None], worn[:, self.mirror_imus], worn)
                alive = torch.where(m[None, :, None], alive[..., self.mirror_imus], alive)
            imu_rot, imu_flag = self.wear(imu_rot, worn, alive, {k: t(v) for k, v in d["imu"].items()})
        feats, points, yaw_q = self.features(sig, imu_rot, imu_flag)
        inv_yaw = qinv(yaw_q)
        gt_rel = qrot(inv_yaw[..., None, :].expand(gt_pos.shape[:-1] + (4,)), gt_pos - gt_pos[..., HEAD:HEAD + 1, :])
        root_local = qmul(inv_yaw, sig["waist_rot"])
        local_m = qto_matrix(rot[..., self.predicted, :])
        f32 = torch.float32
        return {"features": feats.to(f32), "gt_rel": gt_rel.to(f32), "root_rot": qto_matrix(root_local).to(f32),
                "rot6d": matrix_to_6d(local_m).reshape(local_m.shape[:-3] + (-1,)).to(f32),
                "contacts": contacts, "anchor_y": points[..., 0, 1].to(f32)}

    def window_motion(self, d):
        """motion.dataset.window_motion in torch: each window's motion at its tempo, mirrored where asked."""
        W, dev = self.window, self.device
        starts = torch.as_tensor(d["starts"], device=dev)
        if "speed" in d:
            pos = starts[None, :].to(torch.float64) + torch.arange(W, device=dev, dtype=torch.float64)[:, None] \
                * torch.as_tensor(d["speed"], device=dev, dtype=torch.float64)[None, :]
            i0 = pos.floor().long().clamp_max(len(self.root) - 1)
            i1 = (i0 + 1).clamp_max(len(self.root) - 1)
            w = (pos - i0).to(self.dtype)
            rot = qslerp(self.rotations[i0], self.rotations[i1], w[..., None].expand(-1, -1, self.rotations.shape[1]))
            root = self.root[i0] * (1 - w[..., None]) + self.root[i1] * w[..., None]
            contacts = self.contacts[pos.round().long()]
        else:
            idx = starts[None, :] + torch.arange(W, device=dev)[:, None]
            rot, root, contacts = self.rotations[idx], self.root[idx], self.contacts[idx]
        if "mirror" in d:
            m = torch.as_tensor(d["mirror"], device=dev)[None, :, None]
            rot = torch.where(m[..., None], rot[..., self.mirror_joints, :] * rot.new_tensor([1.0, 1.0, -1.0, -1.0]), rot)
            root = torch.where(m, root * root.new_tensor([-1.0, 1.0, 1.0]), root)
            contacts = torch.where(m, contacts.flip(-1), contacts)
        return rot, root, contacts

    def signals(self, world_rot, pos, dn):
        """motion.synth.synthesize_from_pose with DeviceNoise.apply_drawn: head, controllers, waist."""
        n, W = self.noise, self.window
        head_rot, hand_rot = world_rot[..., HEAD, :], world_rot[..., WRISTS, :]
        head_pos = pos[..., HEAD, :] + qrot(head_rot, self.eye.expand(head_rot.shape[:-1] + (3,)))
        hand_pos = pos[..., WRISTS, :] + qrot(hand_rot, self.grip.expand(hand_rot.shape[:-1] + (3,)))
        off = smooth_noise(dn["wander0"], dn["wander"], float(np.exp(-1.0 / (FPS * n.pos_corr_s)))) * n.pos_std_m
        off = off + dn["jitter"] * n.jitter_std_m
        rot_noise = from_axis_angle(dn["rot_axis"], torch.deg2rad(dn["rot_deg"]))
        tt = torch.arange(W, device=self.device, dtype=self.dtype)[:, None] / FPS
        yaw = torch.deg2rad(dn["yaw_offset_deg"] + dn["yaw_drift_deg_s"] * tt)
        waist = qmul(from_yaw(yaw), qmul(rot_noise[..., 3, :], world_rot[..., 0, :]))
        return {"head_pos": head_pos + off[..., 0, :], "head_rot": qnormalize(qmul(rot_noise[..., 0, :], head_rot)),
                "hand_pos": hand_pos + off[..., 1:, :], "hand_rot": qnormalize(qmul(rot_noise[..., 1:3, :], hand_rot)),
                "waist_rot": qnormalize(waist)}

    def wear(self, rot, worn, alive, dn):
        """motion.synth.wear with ImuNoise.apply_drawn and the synchroniser's hold and fade."""
        W = self.window
        mount = from_axis_angle(dn["mount_axis"], torch.deg2rad(dn["mount_deg"]))
        tt = torch.arange(W, device=self.device, dtype=self.dtype)[:, None, None] / FPS
        yaw = torch.deg2rad(dn["yaw_offset_deg"] + dn["yaw_drift_deg_s"] * tt)
        jitter = from_axis_angle(dn["jitter_axis"], torch.deg2rad(dn["jitter_deg"]))
        rot = qnormalize(qmul(from_yaw(yaw), qmul(jitter, qmul(rot, mount[None].expand_as(rot)))))
        flag, rot = fade(alive & (worn[None] > 0), rot, FPS)
        return rot, flag * (worn[None] > 0)

    def features(self, sig, imu_rot, imu_flag):
        """edge.features.sequence_features: the 4 points' positions and velocities in the character frame,
        then each extra IMU's 6D times its flag and the flags. -> (features, points [W,B,4,3], yaw_q)."""
        head = sig["head_pos"] - qrot(sig["head_rot"], self.eye.expand(sig["head_pos"].shape))
        wrists = sig["hand_pos"] - qrot(sig["hand_rot"], self.grip.expand(sig["hand_pos"].shape))
        waist = head - qrot(sig["waist_rot"], self.pelvis_to_head.expand(head.shape))
        pts = torch.cat([head[..., None, :], wrists, waist[..., None, :]], dim=-2)
        prev = torch.cat([pts[:1], pts[:-1]], dim=0)
        yaw_q = from_yaw(yaw_of(sig["waist_rot"]))
        inv = qinv(yaw_q)[..., None, :].expand(pts.shape[:-1] + (4,))
        xz = pts.new_tensor([1.0, 0.0, 1.0])
        local = qrot(inv, pts - pts[..., 3:4, :] * xz)
        vel = qrot(inv, (pts - prev) * FPS)
        feats = [local.flatten(-2), vel.flatten(-2)]
        if imu_flag is not None:
            m = qto_matrix(qmul(qinv(yaw_q)[..., None, :].expand(imu_rot.shape), imu_rot))
            six = matrix_to_6d(m) * imu_flag[..., None]
            feats += [six.flatten(-2), imu_flag]
        else:                      # the 4-point case: no IMU worn (make_batch's with_imus=False keeps the
            feats += [torch.zeros(pts.shape[:2] + (7 * 7,), device=self.device, dtype=self.dtype)]  # 73 columns)
        out = torch.cat(feats, dim=-1)
        assert out.shape[-1] == NUM_POINT_FEATURES + 49
        return out, pts, yaw_q
