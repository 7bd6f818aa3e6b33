"""What the host measures of the pose stream during a replay: arrival, latency, error against the
ground truth, frame-to-frame steps and jerk, in preallocated arrays (a soak measures the runtime's
memory, not the harness's)."""
import numpy as np

from edge import quat
from edge.skeleton import fk


class StreamMetrics:
    """Decoded-pose metrics kept in preallocated arrays, so a long soak measures the runtime's memory,
    not the harness's: per-frame arrival, latency and error, and a 3-frame window for jerk."""

    def __init__(self, ticks, hz, gt_pos, lookahead):
        self.hz, self.gt, self.lookahead = hz, gt_pos, lookahead
        self.seen = np.full(ticks + 2, False)           # np.full: its pages touched now, not over the hours
        self.latency = np.full(ticks + 2, np.nan)
        self.error = np.full(ticks + 2, np.nan)
        self.t = np.full(ticks + 2, np.nan)
        self.step = np.full(ticks + 2, np.nan)           # the largest joint move from the previous frame (m)
        self.jerk_sum, self.jerk_n, self.decoded = 0.0, 0, 0
        self.window = np.zeros((4, 21, 3))
        self.window_frames = np.full(4, -10)
        self.wall = {}                                   # pipeline frame index -> wall time its tick began
        # Every decoded pose's joints by ground-truth frame, for the report's skeleton pictures.
        self.pred = None if gt_pos is None else np.full(np.shape(gt_pos), np.nan)

    def add(self, f, arrived, ticks):
        """f: a decoded PoseFrame; ticks: microsecond tick time -> (pipeline frame index, wall time of its tick)."""
        entry = ticks.get(int(round(f.t * 1e6)))
        if entry is None:
            return
        o = entry[0]
        if not 0 <= o < len(self.seen):
            return
        self.decoded += 1
        self.seen[o] = True
        self.t[o] = f.t
        produced = self.wall.get(o + self.lookahead)
        if produced is not None:
            self.latency[o] = (arrived - produced) * 1000
        _, pos = fk(quat.to_matrix(f.rotations), f.root_pos)
        g = int(round(f.t * self.hz))                                   # ground truth is on the session clock
        if self.gt is not None and self.hz <= g < len(self.gt):         # skip the first second, like eval
            self.error[o] = np.linalg.norm(pos - self.gt[g], axis=-1).mean()
        if self.pred is not None and 0 <= g < len(self.pred):
            self.pred[g] = pos
        self.window = np.roll(self.window, -1, axis=0)
        self.window_frames = np.roll(self.window_frames, -1)
        self.window[-1], self.window_frames[-1] = pos, o
        if self.window_frames[-2] == o - 1:
            self.step[o] = np.linalg.norm(pos - self.window[-2], axis=-1).max()
        if g >= self.hz and np.all(np.diff(self.window_frames) == 1):
            jerk = (self.window[3] - 3 * self.window[2] + 3 * self.window[1] - self.window[0]) * self.hz ** 3
            self.jerk_sum += np.linalg.norm(jerk, axis=-1).mean()
            self.jerk_n += 1


def score(inbox, metrics, ticks_by_us, replug):
    """Fold decoded frames into the metrics (and note the first frame after a re-plug)."""
    while inbox:
        f, arrived = inbox.popleft()
        metrics.add(f, arrived, ticks_by_us)
        if replug[0] is not None and replug[1] is None and f.t >= replug[0] - 1e-9:
            replug[1] = f.t


def write_dump(path, metrics, names, parents, fps):
    """The replay's poses beside the ground truth, in `edge eval --dump`'s format (one .npz), for the
    report's skeleton strip and animation: the decoded span, a frame the host missed holding the last."""
    if metrics.pred is None:
        return None
    have = np.flatnonzero(np.isfinite(metrics.pred[:, 0, 0]))
    if not len(have):
        return None
    a, b = have[0], have[-1] + 1
    pred = metrics.pred[a:b].copy()
    for k in range(1, len(pred)):                  # forward-fill the frames the host did not receive
        if not np.isfinite(pred[k, 0, 0]):
            pred[k] = pred[k - 1]
    np.savez_compressed(path, joint_names=np.array(names), parents=parents, fps=fps,
                        gt_pos=np.asarray(metrics.gt[a:b], np.float32), pred_pos=pred.astype(np.float32),
                        warmup_frames=max(0, int(fps) - a))
    return path
