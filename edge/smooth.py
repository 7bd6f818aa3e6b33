"""The upper body's decoder output, smoothed over time: a one-euro filter (Casiez, Roussel and Vogel,
CHI 2012) on each decoder row's 6D rotations of the spine, chest, neck, collars, shoulders and elbows.

Why: the decoder's torso shakes more than a person's (on val's unseen people the predicted chest's jerk
was 2.73x the truth's, the shoulders' 1.57x), and the arms hang from it, so a user sees the elbows
tremble (1.39x). A one-euro filter follows slow motion closely and lets fast motion through: its
cut-off rises with the speed of the 6D values. The head (the headset's) and the wrists (the
controllers') are not filtered; nor are the legs (foot locks keep them).

Each sample's row keeps its own state, so a sample's filter sees only its own motion. The transition
row (a move from sample c to n at weight a) has none of its own: before each of its frames it takes
(1 - a) c's + a n's state as they were before that frame (blend_into), so a move starts from the
shown sample's filter and lands on the new one's exactly. The samples' states before each frame are
kept per look-ahead slot (remember) for a move's recompute. A revived sample copies the shown one's
(copy_rows). The compiled core runs the same filter (postproc.c, smooth_rows) on the same state
arrays; this is its numpy reference.

    smoother = UpperBodySmoother(rows, slots, fps=60.0, min_cutoff_hz=3.0, beta=1.0)
    smoother.apply(decoder.rot6d, R)         # in place, rows 0..R-1, before FK
"""
import math

import numpy as np

# Predicted joints 1..11 (spine, chest, neck, head, l_collar, l_shoulder, l_elbow, l_wrist, r_collar,
# r_shoulder, r_elbow) are the first 66 of the decoder's 6D values; the head and the left wrist pass
# through (the right wrist is joint 12, outside the span).
SMOOTH_JOINTS = 11
SMOOTH_COLS = SMOOTH_JOINTS * 6
PASS_THROUGH = (3, 7)               # head, l_wrist within the span
MIN_CUTOFF_HZ = 3.0                 # chosen on val's unseen people (model card, "The arms a user sees")
BETA = 1.0                          # cut-off Hz added per unit/s of 6D speed
SPEED_CUTOFF_HZ = 1.0               # the speed estimate's own low-pass (the one-euro paper's d_cutoff)


def smoothing_factor(cutoff_hz, fps):
    """The exponential filter's weight on the new value for a cut-off frequency at a frame rate."""
    return cutoff_hz / (cutoff_hz + fps / (2.0 * math.pi))


class UpperBodySmoother:
    def __init__(self, rows, slots, fps, min_cutoff_hz=MIN_CUTOFF_HZ, beta=BETA):
        if not (min_cutoff_hz >= 0.0 and beta >= 0.0):
            raise ValueError(f"upper-body smoothing: min_cutoff_hz and beta must be >= 0, got {min_cutoff_hz}, {beta}")
        self.fps, self.min_cutoff, self.beta = float(fps), float(min_cutoff_hz), float(beta)
        self.enabled = self.min_cutoff > 0.0
        self.speed_weight = smoothing_factor(SPEED_CUTOFF_HZ, self.fps)
        self.prev = np.zeros((rows, SMOOTH_JOINTS, 6))      # each row's last filtered value
        self.speed = np.zeros((rows, SMOOTH_JOINTS))        # each row's filtered 6D speed per joint
        self.before = np.zeros((slots, rows, SMOOTH_JOINTS, 6))     # the samples' state before each slot's frame
        self.before_speed = np.zeros((slots, rows, SMOOTH_JOINTS))
        self.keep = np.zeros(SMOOTH_JOINTS)                  # 1: the joint passes through unfiltered
        self.keep[list(PASS_THROUGH)] = 1.0
        # scratch, so a frame allocates no arrays
        self._diff = np.zeros((rows, SMOOTH_JOINTS, 6))
        self._sq = np.zeros((rows, SMOOTH_JOINTS, 6))
        self._now = np.zeros((rows, SMOOTH_JOINTS))
        self._alpha = np.zeros((rows, SMOOTH_JOINTS))
        self._views = {}
        self._slots = [(self.before[k], self.before_speed[k]) for k in range(slots)]
        self.fresh = True

    def reset(self):
        """The next apply() starts every row from its own value (a new clip, or a restart)."""
        self.fresh = True

    def prime(self, rot6d, rows):
        """Start rows 0..rows-1 from these values, at rest."""
        self.prev[:rows] = rot6d[:rows, :SMOOTH_COLS].reshape(rows, SMOOTH_JOINTS, 6)
        self.speed[:rows] = 0.0
        self.fresh = False

    def set_row(self, row, values):
        """Row `row` starts again from the 6D values [D] (a healed decoder row)."""
        self.prev[row] = values[:SMOOTH_COLS].reshape(SMOOTH_JOINTS, 6)
        self.speed[row] = 0.0

    def copy_rows(self, src, dst):
        """Rows dst (a slice) take row src's state, now and as each slot kept it (revived samples)."""
        self.prev[dst] = self.prev[src]
        self.speed[dst] = self.speed[src]
        self.before[:, dst] = self.before[:, src:src + 1]
        self.before_speed[:, dst] = self.before_speed[:, src:src + 1]

    def remember(self, slot, samples):
        """Keep the samples' state before this frame, in look-ahead slot `slot`."""
        np.copyto(self.before[slot, :samples], self.prev[:samples])
        np.copyto(self.before_speed[slot, :samples], self.speed[:samples])

    def blend_into(self, c, n, a, dst, slot=None):
        """Row dst's state: (1 - a) row c's + a row n's, as they are now or as slot `slot` kept them."""
        # One statement at a time, so only a few row views live at once (a switch's frame stays small).
        prev, speed = (self.prev, self.speed) if slot is None else self._slots[slot]
        np.multiply(prev[c], 1.0 - a, out=self.prev[dst])
        np.multiply(prev[n], a, out=self._diff[dst])
        np.add(self.prev[dst], self._diff[dst], out=self.prev[dst])
        np.multiply(speed[c], 1.0 - a, out=self.speed[dst])
        np.multiply(speed[n], a, out=self._now[dst])
        np.add(self.speed[dst], self._now[dst], out=self.speed[dst])

    def recompute_views(self, rot6d):
        """Each row of rot6d [K, D] as the [1, 11, 6] view apply_to takes (made once, for a move's recompute)."""
        return [rot6d[k:k + 1, :SMOOTH_COLS].reshape(1, SMOOTH_JOINTS, 6) for k in range(len(rot6d))]

    def apply(self, rot6d, rows):
        """Filter rows 0..rows-1 of rot6d [R, D] float32 in place."""
        if not self.enabled:
            return
        if self.fresh:
            self.prime(rot6d, rows)
        self.apply_to(rot6d[:rows, :SMOOTH_COLS].reshape(rows, SMOOTH_JOINTS, 6), rows)

    def apply_to(self, x, rows, first=0):
        """Filter x [rows, 11, 6] float32 in place, with the state of rows first..first+rows-1."""
        views = self._views.get((rows, first))
        if views is None:               # made once per (rows, first): a frame then makes no new views of its own
            state = slice(first, first + rows)
            views = self._views[rows, first] = tuple(a[state] for a in (
                self.prev, self.speed, self._diff, self._sq, self._now, self._alpha)) + (
                self._alpha[state, :, None], tuple(self._sq[state, :, i] for i in range(6)))
        prev, speed, diff, sq, now, alpha, alpha3, sq_cols = views
        np.subtract(x, prev, out=diff)
        np.multiply(diff, diff, out=sq)
        np.add(sq_cols[0], sq_cols[1], out=now)            # summed in order, as the C loop does (np.sum's
        for col in sq_cols[2:]:                            # reduction allocates a buffer)
            now += col
        np.sqrt(now, out=now)
        now *= self.fps                                    # 6D units a second
        now -= speed
        now *= self.speed_weight
        speed += now                                       # the speed, low-passed
        np.multiply(speed, self.beta, out=alpha)
        alpha += self.min_cutoff                           # the cut-off rises with the speed
        np.add(alpha, self.fps / (2.0 * math.pi), out=now)
        np.divide(alpha, now, out=alpha)                   # smoothing_factor(cut-off, fps)
        np.maximum(alpha, self.keep, out=alpha)            # pass-through joints take the new value whole
        diff *= alpha3
        prev += diff
        np.copyto(x, prev, casting="same_kind")
