"""Latent refinement: move the shown sample's latent until its decoded pose meets the constraints.

SSI can only choose among the samples it drew; a kick that no sample makes stays out of reach. After
the choice, and before IK, the refiner takes a few Gauss-Newton (Levenberg-Marquardt) steps on the
shown sample's latent against the live constraints, with the decoder fixed (DragPoser 4.4), and the
refined latent's GRU state goes forward, so refinement shapes the frames after it too.

The board has no autograd: the Jacobian of the constraints' residuals with respect to the 30 latent
dimensions comes from one batched decoder call on the latent, 30 steps along its axes (0.5: with int8
a smaller step drowns in the activations' per-batch quantisation) and the sample's own latent (what
N=32 costs), then FK of those rows and the terms' residuals on each (forward differences). A step
solves (J J^T + (prior + continuity + damping) I) dz = -(J r + prior and continuity gradients); with
the compiled core everything after the decode is one C call (ep_refine_step; the numpy step here is
its reference). No target live: the latent is let go back to the sample's own over release_s.

Constraint terms (each a small class like the SSI criteria, on and off by config and by what is live):
- TargetReach: a point a joint should reach within a radius during a window of frames (SSI 5.3's
  targets, given by the headset or by `edge ssi-study`); a foot target also pulls that leg's IK goal;
- KeepPose (guard): every joint but the target's limb as the sample's own decode makes it;
- FloorContact (guard): no toe or ankle under the floor, and a planted foot (its lock) stays put;
- ImuOrientation (off by default): each worn IMU's segment as the decoder makes it against its
  measurement (chordal distance; tilt only where heading is not trusted).
Guards join a live term and never move the latent alone. The latent prior (towards the sample's own
latent, which the CVAE drew from its prior) and the continuity with the last frame's are analytic.

Targets are untrusted input: one with a non-finite value, on an unknown joint or farther than
MAX_REACH_M from the pelvis is refused and counted (`refused`), never applied.
"""
import math
from dataclasses import dataclass

import numpy as np

from edge import native
from edge.settings import settings_from
from edge.imus import IMU_JOINTS
from edge.physics import FLOOR_ANKLE, FLOOR_TOE     # the lowest a toe and an ankle joint may go (as the IK's floor)
from edge.physics import LEG_SEGMENTS, leg_gap, leg_pair_distances
from edge.skeleton import ANKLES, JOINT, NUM_JOINTS, TOES

# On by default: targets and the legs' clearance, guarded by KeepPose and FloorContact (guards join when
# a target or LegsApart moves the latent and never move it alone). ImuOrientation is there to turn on:
# measured on val it did not pay (models/MODEL_CARD.md: it raised thighs+shins' mpjpe).
DEFAULT_TERMS = ("targets", "keep", "floor", "legs")
COMPILED_TERMS = ("targets", "keep", "floor", "legs")       # what ep_refine_step computes (others: the numpy step)
MAX_REACH_M = 1.5           # a target farther than this from the pelvis is no reach of the user's


@dataclass
class Target:
    """A point `joint` should reach (world, metres) within `radius`, for frames first..last inclusive."""
    joint: int
    position: np.ndarray
    radius: float = 0.05
    first: int = 0
    last: int = 1 << 62
    weight: float = 1.0
    ramp: bool = True           # the pull grows over the window, full at `last`
    key: object = None          # who set it (the headset's target id): the same key replaces it

    def pull(self, frame):
        """How hard the target pulls at `frame` (0..1): with `ramp`, growing over the window (smoothstep)
        to full at its last frame, the time the point is to be reached, so a foot is not dragged there
        the moment the target appears."""
        if not self.ramp:
            return 1.0
        x = min((frame - self.first + 1) / max(self.last - self.first + 1, 1), 1.0)
        return x * x * (3 - 2 * x)


class RefineContext:
    """What the terms see of one batch of latent rows: world positions after FK with the worn IMUs'
    segments set [R,J,3] (the pose the user sees before IK), the decoder's own world rotations
    [R,J,3,3] (raw_world: no IMU override; only when a term asks), the frame's measurements, the
    shown sample's foot locks, and the frame index."""

    def __init__(self):
        self.frame = 0
        self.positions = self.raw_world = None
        self.seg_m = self.seg_flag = None
        self.lock_pos = self.lock_weight = None
        self.keep, self.kept = np.ones(NUM_JOINTS, bool), NUM_JOINTS     # KeepPose's joints, and how many


class ImuOrientation:
    """Each worn IMU's segment (edge.imus) as the decoder makes it, against its measurement: the chordal
    distance of the two rotations (9 residuals an IMU, weighted by its presence flag), or with
    `tilt_only` the gravity direction in the segment's frame (3: blind to heading, for IMUs whose
    heading is not trusted)."""
    name = "imus"
    needs_raw_world = True
    guard = False
    armed = True                # it reads the sensors every frame

    def __init__(self, weight=1.0, tilt_only=False):
        self.weight, self.tilt_only = weight, tilt_only

    def worn(self, ctx):
        return IMU_JOINTS[ctx.seg_flag[IMU_JOINTS] > 0]

    def size(self, ctx):
        return len(self.worn(ctx)) * (3 if self.tilt_only else 9)

    def residuals(self, ctx):
        j = self.worn(ctx)
        w = np.sqrt(self.weight) * ctx.seg_flag[j]                           # [K]
        R, M = ctx.raw_world[:, j], ctx.seg_m[j]                             # [B,K,3,3], [K,3,3]
        if self.tilt_only:                                                   # world up in each segment's frame
            d = R[..., 1, :] - M[..., 1, :]
        else:
            d = (R - M).reshape(len(R), len(j), 9)
        return (d * w[:, None]).reshape(len(R), -1)


class FloorContact:
    """No toe or ankle under the floor (FLOOR_TOE, FLOOR_ANKLE), and each planted foot's ankle where its
    lock holds it, at the lock's weight (LoBSTR 3.4.1's contacts as a constraint on the whole body: a
    planted foot places the pelvis)."""
    name = "floor"
    needs_raw_world = False
    guard = True                # it joins when another term moves the latent, and never moves it alone

    def __init__(self, weight=1.0, planted=1.0):
        self.weight, self.planted = weight, planted

    def size(self, ctx):
        return 4 + 6

    def residuals(self, ctx):
        P = ctx.positions
        under = np.minimum(P[:, np.r_[TOES, ANKLES], 1] - np.array([FLOOR_TOE] * 2 + [FLOOR_ANKLE] * 2), 0.0)
        hold = (P[:, ANKLES] - ctx.lock_pos) * (np.sqrt(self.planted) * ctx.lock_weight)[:, None]
        return np.concatenate([np.sqrt(self.weight) * under, hold.reshape(len(P), 6)], axis=1)


class TargetReach:
    """SSI 5.3's targets as constraints: while a target is live, its joint's distance beyond the
    radius (3 residuals a target, along the offset)."""
    name = "targets"
    needs_raw_world = False
    guard = False

    def __init__(self, weight=1.0):
        self.weight = weight
        self.targets = []
        # live()'s answer, kept while no window opens or closes and the targets are the same (a frame
        # with a target makes no new list): for frames from .. until - 1, of this list at this length.
        self._live, self._from, self._until, self._of, self._count = [], 0, -1, None, 0

    def live(self, frame):
        """The targets live at `frame`: the same list object until a window opens or closes or a target
        is added or dropped (a refined frame tests it with `is`)."""
        if not (self._from <= frame < self._until and self._of is self.targets and self._count == len(self.targets)):
            self._live = [g for g in self.targets if g.first <= frame <= g.last]
            edges = [e for g in self.targets for e in (g.first, g.last + 1) if e > frame]
            self._from, self._until = frame, min(edges, default=1 << 62)
            self._of, self._count = self.targets, len(self.targets)
        return self._live

    def size(self, ctx):
        return 3 * len(self.live(ctx.frame))

    def residuals(self, ctx):
        out = []
        for g in self.live(ctx.frame):
            d = ctx.positions[:, g.joint] - g.position                       # [B,3]
            dist = np.linalg.norm(d, axis=1, keepdims=True)
            beyond = np.maximum(1.0 - g.radius / np.maximum(dist, 1e-9), 0.0)
            out.append(np.sqrt(self.weight * g.weight * g.pull(ctx.frame)) * d * beyond)
        return np.concatenate(out, axis=1)

    def forget(self, frame):
        """Drop targets whose window has passed."""
        self.targets = [g for g in self.targets if g.last >= frame]


class KeepPose(object):
    """The rest of the body as the sample itself makes it (its decode at its own latent, from the same
    GRU state): each joint's offset from there, but for the limbs a live target moves. A prior in pose
    space: it lets a target move a leg without bending the body the target says nothing about."""
    name = "keep"
    needs_raw_world = False
    guard = True

    def __init__(self, weight=1.0):
        self.weight = weight

    def size(self, ctx):
        return 3 * ctx.kept

    def residuals(self, ctx):
        d = ctx.positions[:, ctx.keep] - ctx.ref_positions[ctx.keep]
        return np.sqrt(self.weight) * d.reshape(len(d), -1)


class LegsApart:
    """SSI 5.3's collision avoidance as a constraint on the shown sample: each pair of a left-leg and a
    right-leg segment (thigh, shin) closer than `clearance` pays the distance it is inside (4 residuals).

    It is live only while `armed`, which the pipeline decides after each frame's pose (arm): the
    shown pose's legs came within clearance + hysteresis of each other with a foot free to move (two
    planted feet are where their locks hold them, and the latent cannot move them apart). So a frame
    whose legs are apart pays nothing, and the refiner runs on the frames that need it (on val, at the
    shipped settings, about 4 % of them; models/MODEL_CARD.md, "Present-frame output")."""
    name = "legs"
    needs_raw_world = False
    guard = False
    moves = tuple(JOINT[f"{s}_{k}"] for s in "lr" for k in ("knee", "ankle", "toe"))    # what KeepPose lets go

    def __init__(self, weight=10.0, clearance=0.14, hysteresis=0.01):
        self.weight, self.clearance, self.hysteresis = weight, clearance, hysteresis
        self.armed = False
        self.segs_addr = native.addr(LEG_SEGMENTS)      # the compiled step's
        self._lib = None
        self._pos = None

    def watch(self, pos):
        """The rows arm() reads the shown pose from: the pipeline's FrameBuffers.pos [R,J,3] (float64,
        C-contiguous; their addresses are taken once)."""
        self._pos = pos
        self._pos_addr, self._row_bytes = native.addr(pos), pos.strides[0]

    def bind(self, lib):
        """Use the compiled core's ep_physical_cost (legs only, at clearance + hysteresis) for arm()."""
        self._lib = lib
        self._zero = np.zeros(2)
        self._contacts = np.zeros(2, np.float32)
        self._feet = np.zeros(4, np.int64)
        self._cost = np.zeros(1)
        self._params = native.PhysicalParams(self.segs_addr, native.addr(self._feet),
                                             self.clearance + self.hysteresis, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0)
        self._addrs = tuple(native.addr(v) for v in (self._contacts, self._zero, self._cost))

    def arm(self, row, lock_weight):
        """Arm the term for the next frame from this frame's shown pose (row `row` of the watched
        positions) and its foot locks' weights [2]."""
        if lock_weight[0] >= 0.99 and lock_weight[1] >= 0.99:
            self.armed = False
        elif self._lib is None:
            self.armed = bool(leg_gap(self._pos[row]) < self.clearance + self.hysteresis)
        else:
            contacts, lift, cost = self._addrs
            self._lib.ep_physical_cost(1, NUM_JOINTS, self._pos_addr + row * self._row_bytes, contacts, lift,
                                       self._params, cost)
            self.armed = self._cost[0] > 0.0

    def size(self, ctx):
        return 4 if self.armed else 0

    def residuals(self, ctx):
        return np.sqrt(self.weight) * np.maximum(self.clearance - leg_pair_distances(ctx.positions), 0.0)


FOOT_OF = {int(a): f for f, a in enumerate(ANKLES)} | {int(t): f for f, t in enumerate(TOES)}
# The joints a target on each joint may move: its limb from the hip or shoulder down.
LIMB_OF = {}
for _side in "lr":
    for _limb in (("hip", "knee", "ankle", "toe"), ("shoulder", "elbow", "wrist")):
        _chain = [JOINT[f"{_side}_{k}"] for k in _limb]
        for _j in _chain:
            LIMB_OF[_j] = _chain


@dataclass(frozen=True)
class RefineSettings:
    """How the refiner steps: K Gauss-Newton steps a frame, the Jacobian's step along each latent axis,
    the analytic terms' weights, and the constraint terms (names of DEFAULT_TERMS and the IMU terms, or
    term objects) with optional {name: weight}. `edge run`'s [refine] section and `--refine` set steps
    and terms; the rest are the tuned defaults."""
    steps: int = 2
    eps: float = 0.5
    prior: float = 3e-4
    continuity: float = 3e-4
    damping: float = 1e-3
    max_step: float = 3.0
    release_s: float = 0.1
    terms: tuple = None
    weights: dict = None
    ik_pull: float = 0.5

    @classmethod
    def parse(cls, value):
        """None/False (off), True (the defaults), a dict of fields, or RefineSettings -> RefineSettings or
        None; an unknown field is refused with the known ones."""
        return settings_from(cls, value, "refine")


class Refiner:
    """K Gauss-Newton steps a frame on one row's latent (see the module's docstring).

    `decoder_session` is the pipeline's decoder model; `forward(slot, rot6d [R,D] float32, rows,
    segments, out)` is the frame path's FK of decoder rows against a ring slot's inputs
    (CompiledFrame.forward_rows, one C call, or NumpyFrame's), into out = (local, world, pos) [R,...];
    each refine() says which slot. compiled = (the C library, the core context) for ep_refine_step."""

    def __init__(self, decoder_session, manifest, forward, settings=None, fps=60.0, compiled=None,
                 jacobian_session=None):
        from edge.inference import Decoder, JacobianBatch
        s = self.settings = RefineSettings() if settings is None else settings
        L, H, F = manifest["latent"], manifest["hidden"], manifest["features"]
        eps = s.eps
        self.L, self.steps, self.eps, self.ik_pull = L, s.steps, eps, s.ik_pull
        self.prior, self.continuity, self.damping, self.max_step = s.prior, s.continuity, s.damping, s.max_step
        # With no term live the latent eases back to the sample's own, by this fraction a frame (a time
        # constant of release_s), so a constraint that ends lets go smoothly (as a foot lock does).
        self.release = 1.0 - np.exp(-1.0 / (fps * s.release_s))
        # The latent, L steps along its axes, and the sample's own latent (KeepPose's reference): on the
        # Jacobian graph (what the rows share computed once) when the models have one, else the decoder's.
        self.batch = (JacobianBatch(jacobian_session, L + 2, L, H, F) if jacobian_session is not None
                      else Decoder(decoder_session, L + 2, L, H, F, recurrent=False))
        self.final = Decoder(decoder_session, 1, L, H, F, recurrent=False)        # the refined latent's decode
        self.forward = forward
        R = L + 2
        self._local = np.zeros((R, NUM_JOINTS, 3, 3))
        self._world = np.zeros((R, NUM_JOINTS, 3, 3))
        self._raw_world = np.zeros((R, NUM_JOINTS, 3, 3))
        self._pos = np.zeros((R, NUM_JOINTS, 3))
        self._raw_pos = np.zeros((R, NUM_JOINTS, 3))
        self._steps = self._axis_steps(eps)
        # The latent being refined, the one the frame started from, and the sample's own (float64 [L]).
        self.z, self.z_prev, self.z_prior = np.zeros(L), np.zeros(L), np.zeros(L)
        self._z_addrs = tuple(native.addr(v) for v in (self.z, self.z_prev, self.z_prior))
        known = {"imus": ImuOrientation, "imus-tilt": lambda: ImuOrientation(tilt_only=True), "floor": FloorContact,
                 "targets": TargetReach, "keep": KeepPose, "legs": LegsApart}
        terms = DEFAULT_TERMS if s.terms is None else s.terms
        self.terms = [known[t]() if isinstance(t, str) else t for t in terms]   # names or term objects
        for name, w in (s.weights or {}).items():       # {term name: weight}
            self.term(name).weight = w
        self._reach = self.term("targets")              # TargetReach, or None when it is not among the terms
        self._legs = self.term("legs")                  # LegsApart, or None
        self._legs_kept = False                         # whether KeepPose's mask lets the legs go
        self.ctx = RefineContext()
        self._live = None               # this frame's live targets (TargetReach.live), as KeepPose's mask was made for
        # The compiled step (ep_refine_step): compiled = (the C library, the pipeline's core context);
        # refine() hands it the frame's ring slot. It takes TargetReach, KeepPose and FloorContact;
        # a frame with the IMU term live takes the numpy step.
        self._c, self._slot = None, 0
        if compiled is not None:
            self._c = compiled
            self._init_compiled(L, R)
            if self._legs is not None:
                self._legs.bind(compiled[0])
        self.refused = {"non_finite": 0, "unknown_joint": 0, "out_of_reach": 0}
        self.applied = 0            # frames refined
        self._displaced = False     # the latent is not yet back at the sample's own
        self.last_cost = (0.0, 0.0)     # the constraints' cost at the last frame's first and last step

    def reset(self):
        """A new take: no latent is displaced and no term is armed from the last take's pose."""
        self._displaced = False
        if self._legs is not None:
            self._legs.armed = False

    # ---- the terms
    def term(self, name):
        return next((t for t in self.terms if t.name == name), None)

    def busy(self):
        """Whether refine has anything to do: a target waiting or live, a latent still let go, an armed
        LegsApart, or a term that reads the sensors every frame. When not, the pipeline skips the stage
        (and pays nothing)."""
        reach = self._reach
        return bool(reach is not None and reach.targets) or self._displaced or any(
            not t.guard and t.name != "targets" and t.weight > 0 and t.armed for t in self.terms)

    def holds(self, frame):
        """Whether the refined sample should stay shown: a target is live, or the latent is still being
        let go. SSI does not switch then (a switch would hand the output to a sample that was not
        refined, through a transition made from the samples' own latents)."""
        reach = self._reach
        return self._displaced or bool(reach is not None and reach.live(frame))

    def remove_target(self, key):
        """Drop the targets added with `key` (the headset's target id); True if there were any."""
        reach = self._reach
        if reach is None:
            return False
        kept = [g for g in reach.targets if g.key != key]
        gone = len(kept) != len(reach.targets)
        reach.targets = kept
        return gone

    def add_target(self, joint, position, radius=0.05, first=0, last=1 << 62, pelvis=None, weight=1.0, key=None):
        """Add a target (joint name or index, world position [3] in metres) unless it is unsafe: a
        non-finite value, an unknown joint, or farther than MAX_REACH_M from `pelvis` [3] (when given).
        Returns the Target, or None (counted in `refused` by reason)."""
        if isinstance(joint, str):
            joint = JOINT.get(joint, -1)
        position = np.asarray(position, dtype=np.float64).reshape(-1)
        numbers = np.array([radius, weight] + list(position[:3]), dtype=np.float64)
        if position.shape != (3,) or not np.isfinite(numbers).all() or radius < 0 or weight < 0:
            self.refused["non_finite"] += 1
            return None
        if not 0 <= int(joint) < NUM_JOINTS:
            self.refused["unknown_joint"] += 1
            return None
        if pelvis is not None and np.linalg.norm(position - pelvis) > MAX_REACH_M:
            self.refused["out_of_reach"] += 1
            return None
        reach = self._reach
        if reach is None:
            return None
        if key is not None:             # a target sent again under its id replaces the last one
            self.remove_target(key)
        g = Target(int(joint), position.copy(), float(radius), int(first), int(last), float(weight), key=key)
        reach.targets.append(g)
        return g

    def live_terms(self, ctx):
        """The terms with something to do this frame (a term without residuals drops out: an
        unplugged IMU's, a target outside its window)."""
        return [t for t in self.terms if t.weight > 0 and t.size(ctx) > 0]

    def foot_pull(self, frame, joint, goal, weight):
        """The live targets on a foot (ankle or toe) as leg IK goals: for each foot, into joint [2],
        goal [2,3] and weight [2] (0: none), the target's joint, point and pull (its term weight times the
        window's ramp, at most `ik_pull`). IK closes what the latent could not. True when any pulls."""
        weight[:] = 0.0
        reach = self._reach
        if reach is None or not self.ik_pull:
            return False
        pulls = False
        for g in reach.live(frame):
            f = FOOT_OF.get(g.joint)
            if f is not None:
                joint[f], goal[f] = g.joint, g.position
                weight[f] = v = self.ik_pull * g.pull(frame)
                pulls = pulls or v > 0
        return pulls

    # ---- one frame
    def refine(self, frame, latent, prior_latent, hidden, features, seg_m, seg_flag, lock_pos, lock_weight, row=0,
               slot=0):
        """Refine `latent` [L] float32 (in place) for this frame: K steps from it against the live terms,
        with the prior towards `prior_latent` and continuity with `latent` as it came in. `hidden` [H]
        is the GRU state the row read, `features` [F] the frame's decoder input, lock_pos [2,3] and
        lock_weight [2] its foot locks (`row` of FootLock's state, where the compiled step reads them);
        `slot` is the frame's ring slot, whose inputs the FK of the moved rows is measured against. Returns the refined row's decode (rot6d [D], contacts [2], GRU state out [H]), or None when no
        term is live."""
        ctx = self.ctx
        self._row, self._slot = row, slot
        ctx.frame, ctx.seg_m, ctx.seg_flag, ctx.lock_pos, ctx.lock_weight = frame, seg_m, seg_flag, lock_pos, lock_weight
        reach = self._reach
        live = reach.live(frame) if reach is not None else ()
        legs = self._legs is not None and self._legs.armed
        if live is not self._live or legs != self._legs_kept:   # a window opened or closed, the targets changed
            if reach is not None and any(g.last < frame for g in reach.targets):
                reach.forget(frame)
                live = reach.live(frame)
            ctx.keep[:] = True
            for g in live:                      # KeepPose holds all but the live targets' limbs
                ctx.keep[LIMB_OF.get(g.joint, [g.joint])] = False
            if legs:                            # and the legs, while LegsApart moves them
                ctx.keep[list(LegsApart.moves)] = False
            ctx.kept = int(ctx.keep.sum())
            self._live, self._legs_kept = live, legs
        terms = self.live_terms(ctx)
        if all(t.guard for t in terms) or self.steps == 0:   # nothing to reach for (the guards alone would
            return self._let_go(latent, prior_latent, hidden, features)   # only hold), or no steps to spend
        self._terms, self._raw = terms, any(t.needs_raw_world for t in terms)
        self._c_on = self._prepare_compiled(terms)
        b = self.batch
        b.features[:] = features
        b.hidden[0][:] = hidden
        self.z_prev[:] = latent
        self.z[:] = latent
        self.z_prior[:] = prior_latent
        b.latent[self.L + 1] = prior_latent     # KeepPose's reference row: the same for the frame's steps
        first = cost = self.step()
        for _ in range(self.steps - 1):
            cost = self.step()
        latent[:] = self.z
        out = self._decode(latent, hidden, features)
        self.applied += 1
        self._displaced = True
        self.last_cost = (first, cost)
        return out

    def _init_compiled(self, L, R):
        MAX_TARGETS = 8
        self._c_max_m = (3 * MAX_TARGETS + 3 * NUM_JOINTS + 10 + 4 + 7) // 8 * 8     # the C step pads to 8
        self._c_buf = {"pos": np.zeros((R, NUM_JOINTS, 3)), "r": np.zeros((R, self._c_max_m)), "A": np.zeros((L, L)),
                       "jt": np.zeros((L, self._c_max_m)),
                       "g": np.zeros(L), "joint": np.zeros(MAX_TARGETS, np.int64), "tpos": np.zeros((MAX_TARGETS, 3)),
                       "radius": np.zeros(MAX_TARGETS), "w": np.zeros(MAX_TARGETS), "keep": np.ones(NUM_JOINTS, np.uint8)}
        c = self._c_buf
        self._c_args = native.RefineArgs(
            rot6d=native.addr(self.batch.rot6d), rot6d_stride=self.batch.rot6d.shape[1], L=L, eps=self.eps,
            pos=native.addr(c["pos"]), r=native.addr(c["r"]), A=native.addr(c["A"]), g=native.addr(c["g"]),
            jt=native.addr(c["jt"]),
            max_m=self._c_max_m, target_joint=native.addr(c["joint"]), target_pos=native.addr(c["tpos"]),
            target_radius=native.addr(c["radius"]), target_w=native.addr(c["w"]), keep=native.addr(c["keep"]),
            prior=self.prior, continuity=self.continuity, damping=self.damping, max_step=self.max_step)
        self._c_max_targets = MAX_TARGETS
        # ep_refine_fill's arguments: the refiner's own latent into the batch's first L + 1 rows
        self._fill_args = (L, self._z_addrs[0], native.checked_addr(self._steps, np.float32, (L, L), "refine steps"),
                           native.checked_addr(self.batch.latent, np.float32, (R, L), "refine batch latent"))
        self._c_on = False          # this frame's terms are all the compiled step's
        self._c_live = self._c_settings = None      # what the arguments were last filled for
        self._c_legs_kept = False

    def _prepare_compiled(self, terms):
        """This frame's live terms into the compiled step's arguments; False if it cannot take them. The
        targets' joints, points and radii and the keep mask change only with the live set; their pulls
        (the windows' ramps) every frame."""
        if self._c is None or any(t.name not in COMPILED_TERMS for t in terms):
            return False
        a, c, ctx = self._c_args, self._c_buf, self.ctx
        live = self._live
        if len(live) > self._c_max_targets:
            return False
        if live is not self._c_live or self._legs_kept != self._c_legs_kept:     # KeepPose's mask changed
            for i, g in enumerate(live):
                c["joint"][i], c["tpos"][i], c["radius"][i] = g.joint, g.position, g.radius
            c["keep"][:] = ctx.keep
            self._c_live, self._c_legs_kept = live, self._legs_kept
        w, frame = c["w"], ctx.frame
        for i, g in enumerate(live):
            w[i] = math.sqrt(self._reach.weight * g.weight * g.pull(frame))
        settings = (self.prior, self.continuity, self.damping, self.max_step, self.eps)
        if settings != self._c_settings:
            a.prior, a.continuity, a.damping, a.max_step, a.eps = self._c_settings = settings
        a.n_targets, a.keep_on, a.floor_on, a.legs_on = len(live), 0, 0, 0
        for t in terms:
            if t.name == "keep":
                a.keep_on, a.keep_w = 1, math.sqrt(t.weight)
            elif t.name == "floor":
                a.floor_on, a.floor_w, a.planted_w = 1, math.sqrt(t.weight), math.sqrt(t.planted)
                a.lock_row = self._row          # the C step reads the row's locks from the core's FootLock state
            elif t.name == "legs":
                a.legs_on, a.legs_w, a.legs_clear, a.legs_segs = 1, math.sqrt(t.weight), t.clearance, t.segs_addr
        return True

    def step(self, z=None, z_prev=None, zp=None):
        """One Levenberg-Marquardt step on z [L] float64 in place, from the Jacobian at z; z_prev is the
        latent the frame started from (continuity), zp the sample's own (prior); by default the
        refiner's own (self.z, self.z_prev, self.z_prior, as refine fills them). Returns the
        constraints' cost at z. The compiled step when this frame's terms allow (ep_refine_step), else numpy."""
        if z is None:
            z, z_prev, zp = self.z, self.z_prev, self.z_prior
            addrs = self._z_addrs
        else:
            addrs = None
        if self._c_on:
            lib, core = self._c
            if addrs:       # the refiner's own latent: its batch rows filled in C (a fifth of _fill_batch's cost)
                lib.ep_refine_fill(*self._fill_args)
            else:
                self._fill_batch(z, self._steps)
            self.batch.step()
            cost = lib.ep_refine_step(core, self._c_args, self._slot, *(addrs or map(native.addr, (z, z_prev, zp))))
            if cost >= 0:
                return cost
        r, J = self.jacobian(z)
        A = J @ J.T
        A[np.diag_indices_from(A)] += self.prior + self.continuity + self.damping
        g = J @ r + self.prior * (z - zp) + self.continuity * (z - z_prev)   # the gradient of half the cost
        dz = -np.linalg.solve(A, g)
        n = np.linalg.norm(dz)
        if n > self.max_step:
            dz *= self.max_step / n
        z += dz
        return float(r @ r)

    def jacobian(self, z, eps=None):
        """The live terms' residuals at latent z [L] (r [m]) and their Jacobian J [L,m] (d r / d z_k), by
        forward differences of step eps (default self.eps) from one batched decode of z, z + eps e_k and
        the sample's own latent (KeepPose's reference). The batch's features and GRU state, the live
        terms and the context are this frame's (set by refine)."""
        eps = self.eps if eps is None else eps
        self._fill_batch(z, self._steps if eps == self.eps else self._axis_steps(eps))
        r = self._residuals(self._terms, self._raw)[:self.L + 1]      # [L+1, m]
        return r[0], (r[1:] - r[0]) / eps

    def residuals_at(self, z):
        """The live terms' residuals [m] at latent z (every batch row decoded at z): for checking jacobian."""
        self._fill_batch(z, 0.0)
        return self._residuals(self._terms, self._raw)[0]

    def _fill_batch(self, z, steps):
        """The batch's first L + 1 latents: z, then z + steps[k] along each axis k (steps [L,L], or 0: z
        in every row). The last row, the sample's own latent, refine sets once a frame."""
        b, L = self.batch, self.L
        b.latent[:L + 1] = z
        b.latent[1:L + 1] += steps

    def _axis_steps(self, eps):
        """[L, L] float32: eps along each axis."""
        return np.eye(self.L, dtype=np.float32) * np.float32(eps)

    def _let_go(self, latent, prior_latent, hidden, features):
        """No term live: ease the latent back towards the sample's own; None once it is there."""
        gap = prior_latent - latent
        if not np.abs(gap).max() > 1e-3:
            latent[:] = prior_latent
            self._displaced = False
            return None
        latent += np.float32(self.release) * gap
        return self._decode(latent, hidden, features)

    def _decode(self, latent, hidden, features):
        """One row's decode at `latent`: (rot6d [D], contacts [2], GRU state out [H])."""
        f = self.final
        f.features[:] = features
        f.hidden[0][:] = hidden
        f.latent[0] = latent
        f.step()
        return f.rot6d[0], f.contacts[0], f.hidden[1][0]

    def _residuals(self, terms, raw):
        b, ctx = self.batch, self.ctx
        b.step()
        R = b.rows
        self.forward(self._slot, b.rot6d, R, True, (self._local[:R], self._world[:R], self._pos[:R]))
        ctx.positions, ctx.ref_positions = self._pos[:R], self._pos[R - 1]
        if raw:
            self.forward(self._slot, b.rot6d, R, False, (self._local[:R], self._raw_world[:R], self._raw_pos[:R]))
            ctx.raw_world = self._raw_world[:R]
        return np.concatenate([t.residuals(ctx) for t in terms], axis=1)
