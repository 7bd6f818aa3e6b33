"""Adaptive N: a deadline watchdog that decides how many SSI samples to run.

Feed it every frame's response time (release to done, ms); it answers the N for the next frame, and
the pipeline changes N without a visible pop (Pipeline.set_samples). `steer` does both.

Lowering is fast and multiplicative: a missed deadline, or two frames in ten slower than `high` x
the frame period (one such frame can be a scheduling hiccup that N cannot fix), cuts N at once, at
least by half and in proportion to how late the frame was (4x over `high` cuts N to 1/4), then waits
`cooldown` frames after the pipeline has applied the change before judging again.
Contention arrives all at once (other processes take most of the core), and one ladder step saves
only ~10 % of a frame, because much of a frame's cost does not depend on N.
Raising is slow and one ladder step at a time: after `hold` frames at the current N of which at
most 10 % were slower than `low` x the period. A raise that proves too much (a late frame within
`probation` frames) is undone, back to the N that fitted, and the hold before the next try doubles
(up to `max_hold`), so a busy board is not probed every few seconds; `calm` frames without a
lowering bring the hold back to its base. A board that has gone quiet (no frame slower than `low`
in the judged window) is climbed at the base hold whatever the doubled one says, so N comes back
within seconds of the contention ending.
"""
from collections import deque

CHANGE_HISTORY = 1000      # a service that runs for days keeps the last thousand changes of N

LADDER = (1, 2, 4, 8, 16, 24, 32, 48, 64, 96, 128)


class SampleGovernor:
    def __init__(self, period_ms, max_samples, start=None, high=0.75, low=0.45, hold=60, max_hold=1920,
                 cooldown=6, probation=240, calm=3600):
        if not 0 < low < high <= 1:
            raise ValueError("need 0 < low < high <= 1 (fractions of the frame period)")
        self.ladder = [n for n in LADDER if n < max_samples] + [max_samples]
        self.period_ms, self.high_ms, self.low_ms = period_ms, high * period_ms, low * period_ms
        self.base_hold, self.max_hold, self.hold = hold, max_hold, hold
        self.cooldown, self.probation, self.calm = cooldown, probation, calm
        self.level = len(self.ladder) - 1 if start is None else self._level_at_most(start)
        self.window = hold // 2               # frames judged before a raise (the newest ones)
        self._slow = bytearray(self.window)   # ring of "slower than low" flags, no allocation per frame
        self._slow_count = 0
        self._over = bytearray(10)            # the last ten frames: slower than high?
        self._over_count = 0
        self.frame = 0
        self.since_change = 0
        self.since_lower = cooldown + 1       # the first late frame acts at once
        self.last_raise_at = None
        # (frame, from N, to N, reason): the most recent CHANGE_HISTORY, for reports; change_count counts all
        self.changes = deque(maxlen=CHANGE_HISTORY)
        self.change_count = 0

    @property
    def samples(self):
        return self.ladder[self.level]

    def _level_at_most(self, n):
        return max(i for i, v in enumerate(self.ladder) if v <= max(n, self.ladder[0]))

    def observe(self, frame_ms, running=None):
        """One frame's response time (ms), and the N it ran with if known -> the N to run next."""
        self.frame += 1
        self.since_change += 1
        self.since_lower = 0 if running is not None and running > self.samples else self.since_lower + 1
        i = self.frame % self.window
        slow = 1 if frame_ms > self.low_ms else 0
        self._slow_count += slow - self._slow[i]
        self._slow[i] = slow
        j = self.frame % 10
        over = 1 if frame_ms > self.high_ms else 0
        self._over_count += over - self._over[j]
        self._over[j] = over
        late = over and (frame_ms > self.period_ms or self._over_count >= 2)
        if late and self.level > 0 and self.since_lower > self.cooldown:
            if self.last_raise_at is not None and self.frame - self.last_raise_at <= self.probation:
                self._change(self.level - 1, "undo")                  # that raise was too much:
                self.hold = min(2 * self.hold, self.max_hold)        # back, and wait longer next time
                self.last_raise_at = None
            else:
                cut = min(0.5, self.high_ms / frame_ms)
                self._change(self._level_at_most(int(self.samples * cut)), "late")
            self.since_lower = 0
        elif (self.level < len(self.ladder) - 1 and self._slow_count <= self.window // 10
              and self.since_change >= (self.base_hold if self._slow_count == 0 else self.hold)):
            self._change(self.level + 1, "slack")
            self.last_raise_at = self.frame
        if self.since_lower >= self.calm:
            self.hold = self.base_hold
        return self.samples

    def steer(self, pipeline, frame_ms):
        """Observe a frame of `pipeline` (anything with `samples` and `set_samples`) and pass a new N on."""
        before = self.samples
        n = self.observe(frame_ms, pipeline.samples)
        if n != before:
            pipeline.set_samples(n)

    def _change(self, level, reason):
        self.changes.append((self.frame, self.samples, self.ladder[level], reason))
        self.change_count += 1
        self.level = level
        self.since_change = 0
