"""One frame's memory and the two ways through it.

A frame goes features -> decode -> pose -> select -> refine -> emit (edge.pipeline runs them in that
order). Two paths implement the stages around the decoder and the refiner, on the same memory:
CompiledFrame (edge.frame_compiled: four C calls, what the board runs) and NumpyFrame
(edge.frame_numpy: the numpy reference they are tested against, and the fallback without a C
compiler). This module holds what they share: FrameBuffers (the memory, allocated once), FramePath
(the stages' interface), the output Pose and the geometry both use.
"""
from dataclasses import dataclass, field

import numpy as np

from edge import quat
from edge.imus import NUM_IMUS
from edge.physics import lowest_point, support
from edge.skeleton import ANKLES, JOINT, LEVELS, NUM_JOINTS, NUM_PREDICTED, OFFSETS, PARENTS, TOES

# Legs (foot locks) and arms (controllers) solved in one batched IK call.
LIMB_CHAINS = np.array([[JOINT[f"{s}_{a}"], JOINT[f"{s}_{b}"], JOINT[f"{s}_{c}"]]
                        for a, b, c in (("hip", "knee", "ankle"), ("shoulder", "elbow", "wrist")) for s in "lr"])
LIMB_POLES = np.array([[0.0, 0.0, 1.0]] * 2 + [[0.0, 0.0, -1.0]] * 2)   # knees bend forward, elbows back
NECK, SPINE, CHEST = JOINT["neck"], JOINT["spine"], JOINT["chest"]
POSITION_LIMIT_M = 30.0     # a tracked position farther out is no tracked space's (step refuses it; POSE_FRAME's root ends at 32.767 m)


@dataclass
class Pose:
    """One output frame: world joint positions [J,3] (m), local joint rotations [J,3,3], foot contacts [2]."""
    frame: int = -1
    positions: np.ndarray = field(default_factory=lambda: np.zeros((NUM_JOINTS, 3)))
    rotations: np.ndarray = field(default_factory=lambda: np.zeros((NUM_JOINTS, 3, 3)))
    contacts: np.ndarray = field(default_factory=lambda: np.zeros(2))
    sample: int = 0
    transition: bool = False


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
        # The Signals fields Pipeline._load_frame_in copies, each with its [1,...] view of frame_in.
        self.input_fields = [(k, v[None]) for k, v in self.inputs.items() if imus or not k.startswith("imu")]
        # A live target on a foot of the refined row: the row (-1: none), per foot the target's joint
        # (ankle or toe), point and pull on the leg's IK goal (edge.refine.Refiner.foot_pull).
        self.target_row = np.full(1, -1, np.int64)
        self.target_joint = np.array(ANKLES, np.int64)
        self.target_goal = np.zeros((2, 3))
        self.target_weight = np.zeros(2)


@dataclass(frozen=True)
class FrameSpec:
    """The settings the frame paths read, fixed when the pipeline is made."""
    fps: float
    body_scale: float               # the canonical body's size against the calibrated user's
    foot_ik: bool
    arm_ik: bool
    elbow_from_hand: float          # how far the hand's direction turns the elbow (edge.ik.swivel_to_hands)
    imus: int                       # extra IMU slots the decoder reads (0 or NUM_IMUS)
    orientations: bool             # the decoder reads the headset's and controllers' orientations
    segments: bool                  # worn IMUs set their segments' rotations
    n_features: int
    lookahead: int
    max_samples: int                # N the buffers are allocated for


@dataclass(frozen=True)
class FrameState:
    """The memory the frame paths work in, each part owned by the pipeline's component that keeps it:
    the look-ahead ring (edge.ssi.LookaheadBuffer), the samples' latents, the foot locks (edge.ik.FootLock),
    the upper body's filter (edge.smooth), a move's recompute decoder (edge.inference), the output pose,
    the autoencoder and its plausibility scorer, and the selection criteria. The live decoder is not
    here: a change of N makes a new one, which the pipeline binds to each path (bind_decoder)."""
    buffer: object
    latents: np.ndarray
    feet: object
    smoother: object
    recompute: object
    out: Pose
    autoencoder: object
    scorer: object
    criteria: object


class FramePath:
    """The stages of a frame around the two ONNX calls, as Pipeline.step calls them. Both paths work
    in the pipeline's FrameBuffers and look-ahead ring (edge.ssi.LookaheadBuffer), slot s a frame:

      inputs(sig, s, N, blend) -> bool    features: body points, features and tracker matrices into
                                          slot s and the decoder's input (False: the frame is not sane)
      poses(s, rows, N, blend, keep_world, shown) -> bool
                                          pose: FK hung from the head, foot locks, leg and arm IK of
                                          every decoder row (False: a row went non-finite); `shown`
                                          is the sample shown when no move is live
      judge(s, N, c, margin) -> int       select: the default criteria in one call (fused_criteria)
      switch_to(s, N, c, margin) -> int   select: SSI's test on slot s's N costs
      emit(s, row, out)                   emit: the output pose of ring slot s, row `row`
      ring_changed()                      ring rows were rewritten after poses() (a move, a change of N)
      forward_rows(s, rot6d, rows, segments, out)
                                          FK of decoder rows against slot s's inputs (the refiner's
                                          and the heading observer's)
    """

    ae_ready = None             # the scorer whose autoencoder input this path prepares (None: the scorer does)
    fused_criteria = None       # the criteria judge() computes in one call (None: each criterion judges itself)

    def reset(self):
        """A new take: the velocity features start again."""

    def bind_decoder(self, dec):
        """The decoder whose buffers the path reads (again after set_samples makes a new one)."""
        self.decoder = dec

    def set_target_row(self, row):
        """The decoder row a live foot target pulls (-1: none)."""

    def ring_changed(self):
        """Rows of the ring were rewritten after poses() (a move's recompute, a change of N): a pose the
        path kept for emit() is stale."""

    def inputs(self, sig, s, N, blend):
        raise NotImplementedError

    def poses(self, s, rows, N, blend, keep_world, shown):
        raise NotImplementedError

    def judge(self, s, N, c, margin):
        raise NotImplementedError(f"{type(self).__name__} judges no criteria in one call (fused_criteria is None)")

    def smooth_recomputed(self, k, first):
        """The upper body's filter (edge.smooth) on row k of a move's recompute, with the state of row `first`."""
        raise NotImplementedError

    def switch_to(self, s, N, c, margin):
        raise NotImplementedError

    def emit(self, s, row, out):
        raise NotImplementedError

    def forward_rows(self, s, rot6d, rows, segments, out):
        raise NotImplementedError


class RowFk:
    """FK of one decoder row of a ring slot, without the IMU override: `fk(s, row, out)` fills out =
    (local, world, pos) [1,...]. What the heading observer compares the IMUs with when the decoder is
    its reference; made from the frame path and the ring it reads, so the observer needs neither."""

    def __init__(self, path, rot6d):
        self.path, self.rot6d = path, rot6d         # a FramePath; the ring's decoded rows [slots,rows,D]

    def __call__(self, s, row, out):
        self.path.forward_rows(s, self.rot6d[s, row:row + 1], 1, False, out)
