"""How late the board is: each tick's own time, and each sent pose's age and motion-to-pose lag.

A pose's age runs from the newest tracker sample its tick used reaching the board to the pose leaving
it; its motion-to-pose lag adds the SSI look-ahead the frame was held for. Both go into histograms over
the whole run and a ring of the last poses for the status line; nothing is allocated per tick.
"""
import math
from collections import deque

import numpy as np

AGE_WINDOW = 600             # poses the status line's age and lag cover (10 s at 60 Hz)
AGE_BIN_MS, AGE_BINS = 0.1, 20_000      # the whole run's age and lag histograms: 0.1 ms bins up to 2 s
FRAME_WINDOW = 600           # ticks the frame-time percentiles cover


def percentiles(ring):
    """p50 and p99 of a ring's filled entries (NaN: not yet written); zeros before any."""
    x = ring[np.isfinite(ring)]
    return {"p50": float(np.median(x)), "p99": float(np.percentile(x, 99))} if len(x) else {"p50": 0.0, "p99": 0.0}


def age_bin(ms):
    """The histogram bin of a time in ms (below 0 in the first, beyond the range in the last)."""
    return min(max(int(ms / AGE_BIN_MS), 0), AGE_BINS - 1)


def histogram_percentiles(hist):
    """p50, p99 and the largest of a run's histogram (AGE_BIN_MS bins; the last holds everything beyond),
    each the upper edge of its bin."""
    n = int(hist.sum())
    if not n:
        return {"p50": 0.0, "p99": 0.0, "max": 0.0, "poses": 0}
    c = np.cumsum(hist)
    at = lambda q: float((np.searchsorted(c, q * n) + 1) * AGE_BIN_MS)    # noqa: E731
    return {"p50": at(0.5), "p99": at(0.99), "max": float((np.flatnonzero(hist)[-1] + 1) * AGE_BIN_MS), "poses": n}


class Latency:
    """The frame times of the last FRAME_WINDOW ticks and the poses' age and lag (see the module)."""

    def __init__(self, clock):
        self.clock = clock
        self.frame_ms = deque(maxlen=FRAME_WINDOW)
        self.age_hist = np.zeros(AGE_BINS, np.int64)
        self.lag_hist = np.zeros(AGE_BINS, np.int64)
        self.lag_ms = np.full(AGE_WINDOW, np.nan)
        self._ages = 0

    def frame(self, elapsed_s):
        """One tick took elapsed_s seconds (perf_counter)."""
        self.frame_ms.append(elapsed_s * 1000)

    def pose(self, newest_rx, held_s):
        """A pose just left: newest_rx is when the newest sample its tick used arrived (service clock),
        held_s how long the look-ahead held its frame."""
        if not math.isfinite(newest_rx):
            return
        age = (self.clock() - newest_rx) * 1000.0
        lag = age + 1000.0 * held_s
        self.lag_ms[self._ages % AGE_WINDOW] = lag
        self._ages += 1
        self.age_hist[age_bin(age)] += 1
        self.lag_hist[age_bin(lag)] += 1

    def summary(self):
        fm = np.array(self.frame_ms) if self.frame_ms else np.zeros(1)
        return {"frame_ms": {"p50": float(np.median(fm)), "p99": float(np.percentile(fm, 99))},
                "pose_age_ms": histogram_percentiles(self.age_hist),
                "motion_to_pose_lag_ms": histogram_percentiles(self.lag_hist),
                "motion_to_pose_lag_ms_last_10s": percentiles(self.lag_ms)}
