"""SSI's decisions (section 3.2), apart from the stage code: when the shown sample is an outlier, which
sample to move to, the schedule of the move, and the look-ahead ring that lets a move start in the past.

Every sample keeps its latent for the whole run. When the current sample's cost is an outlier at the
newest frame, the best other sample is chosen (3.2.2) and the output moves to it over T frames by
interpolating both the latent and the decoder's GRU state (3.2.3), starting at the oldest frame not
yet output, tau frames back (3.2.4). A new move waits until the last one has been sent, so moves
never overlap. The pipeline (edge.pipeline) asks `Switcher` what to do and does the decoding.
"""
from collections import deque

import numpy as np

from edge.ik import smoothstep

SWITCH_HISTORY = 10_000     # switches kept (hours of a take; edge eval reads them per take)


def transition_weight(k, T):
    """Blend weight of step k (0-based) of a T-frame transition: SSI 3.2.3 interpolates linearly in
    latent and GRU state; we ease the schedule in and out (smoothstep) so the motion has no velocity
    step at either end, which is what a jerk metric sees."""
    return smoothstep((np.asarray(k) + 1.0) / T)


def is_outlier(cost, c, margin=0.0):
    """SSI eq. 2: r = median - min over all samples. We test the current sample's excess over the best,
    cost[c] - min > 2r; the literal cost[c] > 2r compares an absolute error with a spread and fires on
    nearly every frame. The excess must also exceed `margin` (the manifest's `switch_margin`): where
    most samples cost nothing (the physical criterion), r is 0 and any blemish would switch."""
    lo = cost.min()
    return bool(cost[c] - lo > max(2.0 * (median(cost) - lo), margin))


def median(x):
    """np.median of a 1-D array: the same value, without its general-purpose overhead (~9 us per frame)."""
    k = len(x) // 2
    if len(x) % 2:
        return np.partition(x, k)[k]
    part = np.partition(x, (k - 1, k))
    return (part[k - 1] + part[k]) / 2.0


def best_other(cost, c):
    """SSI 3.2.2: the sample with the smallest cost among the others."""
    keep = cost[c]
    cost[c] = np.inf
    n = int(np.argmin(cost))
    cost[c] = keep
    return n


def switch_to(cost, c, margin=0.0):
    """The sample to move to from c at this frame's costs, or -1 to stay (ep_switch_to in C)."""
    return best_other(cost, c) if is_outlier(cost, c, margin) else -1


class Switcher:
    """Which sample is shown at each output frame, and the move under way.

    `trans` is (from, to, first frame, length) of the latest move; `switches` keeps the most recent
    SWITCH_HISTORY as (detected at, first frame, from, to), and switch_count counts them all (a
    service runs for days and switches about once a second)."""

    def __init__(self, lookahead, length):
        self.lookahead, self.length = lookahead, length
        self._weights = [float(w) for w in transition_weight(np.arange(length), length)]   # per step of a move
        self.reset()

    def reset(self):
        self.current = 0
        self.trans = None
        self.trans_end = -1
        self.switches = deque(maxlen=SWITCH_HISTORY)
        self.switch_count = 0

    def live(self, t):
        """Whether frame t is inside the running move (the decoder's spare row carries it)."""
        return self.trans is not None and t <= self.trans_end

    def weight(self, t):
        """The move's blend weight at frame t (0: the sample it leaves, 1: the one it reaches)."""
        return self._weights[t - self.trans[2]]

    def free(self, t):
        """Whether a new move may start at frame t: the last one has been sent."""
        return t - self.lookahead > self.trans_end

    def start(self, n, t):
        """Move from the current sample to n, detected at frame t: from the oldest frame not yet
        output (3.2.4). Returns the first frame."""
        s0 = max(t - self.lookahead, 0)
        c = self.current
        self.trans, self.trans_end = (c, n, s0, self.length), s0 + self.length - 1
        self.switches.append((t, s0, c, n))
        self.switch_count += 1
        self.current = n
        return s0

    def sample_at(self, o):
        """The sample that owns output frame o: before a running move's first frame, its source."""
        if self.trans is not None and o < self.trans[2]:
            return self.trans[0]
        return self.current

    def shown_during_move(self):
        """The sample a frame inside a move belongs to (the one it reaches)."""
        return self.trans[1] if self.trans else self.current


class LookaheadBuffer:
    """Fixed-memory ring buffer of the tau+1 most recent frames for all N samples, allocated once.

    It keeps what each row's pose is made from, not the pose: the decoder's 6D output, the leg IK's
    goals and weights, and the frame's tracker inputs. The pose of the one row a frame shows is made
    again when the frame is sent (bit for bit the live one): 6D is a sixth of a pose's bytes, and a
    frame at N=100 then writes 60 KB here instead of 360 KB.

    Rows are the N samples and one spare (row N) that a transition's output uses: a frame whose
    override is set shows row trans_row[slot] (the live N when it was written)."""

    def __init__(self, slots, samples, hidden, n_features, rot_dim, joints):
        S, N = slots, samples
        self.slots = S
        self.frame = np.full(S, -1, np.int64)
        self.features = np.zeros((S, n_features), np.float32)
        self.hidden_in = np.zeros((S, N, hidden), np.float32)
        self.rot6d = np.zeros((S, N + 1, rot_dim), np.float32)
        self.contacts = np.zeros((S, N + 1, 2), np.float32)
        self.leg_goal = np.zeros((S, N + 1, 2, 3))      # where the leg IK draws each row's ankles
        self.leg_weight = np.zeros((S, N + 1, 2))       # at what weight (samples: 1, their lock's pull is in the goal)
        self.lock_weight = np.zeros((S, N, 2))          # the samples' lock weights (0 free .. 1 locked)
        self.cost = np.zeros((S, N))
        # The frame's tracker inputs to the post-processing.
        self.anchor = np.zeros((S, 3))
        self.waist_m = np.zeros((S, 3, 3))
        self.wrists = np.zeros((S, 2, 3))
        self.hand_m = np.zeros((S, 2, 3, 3))
        self.head_m = np.zeros((S, 3, 3))
        # The worn IMUs' measured segment rotations and flags, per joint (flag 0: no IMU there).
        self.seg_m = np.zeros((S, joints, 3, 3))
        self.seg_flag = np.zeros((S, joints))
        # Transition output that overrides a sample's own pose for a frame: row trans_row[s].
        self.override = np.zeros(S, bool)
        self.trans_row = np.zeros(S, np.int64)

    def slot(self, frame):
        return frame % self.slots

    def nbytes(self):
        return sum(v.nbytes for v in vars(self).values() if isinstance(v, np.ndarray))
