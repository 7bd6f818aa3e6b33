"""Adaptive N and K: a deadline watchdog that decides how many SSI samples and refinement steps to run.

Feed it every frame's response time (release to done, ms); it answers the N (and K) for the next
frame, and the pipeline changes N without a visible pop (Pipeline.set_samples) and K from the next
frame (Pipeline.set_refine_steps). `steer` does both.

N and K move together along one ladder of rungs (see `rungs`): K refinement steps a frame only cost
while a target is live, so they take their place between the N steps by what they buy. One step
reaches a kick almost as well as two (val, N=1: high kicks 0.202x the unrefined apex error at K=1,
0.187x at K=2), so the first step comes right after N=1, and the others once N reaches SSI's 32.

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
from dataclasses import dataclass

CHANGE_HISTORY = 1000      # a service that runs for days keeps the last thousand changes of N

LADDER = (1, 2, 4, 8, 16, 24, 32, 48, 64, 96, 128)
FULL_STEPS_FROM = 32        # the N after which refinement gets all its steps


def rungs(max_samples, max_steps=0):
    """The (N, K) pairs the governor moves along, cheapest first: N up the LADDER to max_samples; with
    max_steps > 0, K = 1 from the rung after (1, 0), and K = 2..max_steps once N reaches
    FULL_STEPS_FROM (or max_samples, if smaller), kept for every larger N."""
    ns = [n for n in LADDER if n < max_samples] + [max_samples]
    if max_steps <= 0:
        return [(n, 0) for n in ns]
    full_at = min(FULL_STEPS_FROM, ns[-1])
    out = [(1, 0)]
    for n in ns:
        if n < full_at:
            out.append((n, 1))
        elif n == full_at:
            out += [(n, k) for k in range(1, max_steps + 1)]
        else:
            out.append((n, max_steps))
    return out


@dataclass(frozen=True)
class GovernorSettings:
    """When the watchdog acts (the module's docstring): `high` and `low` are fractions of the frame
    period; `hold`, `max_hold`, `cooldown`, `probation` and `calm` are frames."""
    high: float = 0.75
    low: float = 0.45
    hold: int = 60
    max_hold: int = 1920
    cooldown: int = 6
    probation: int = 240
    calm: int = 3600


class SampleGovernor:
    def __init__(self, period_ms, max_samples, start=None, max_steps=0, settings=None):
        """period_ms: the frame period; max_samples, max_steps: the top of the ladder (rungs); start: the
        N to start at (default the top)."""
        s = self.settings = GovernorSettings() if settings is None else settings
        if not 0 < s.low < s.high <= 1:
            raise ValueError("need 0 < low < high <= 1 (fractions of the frame period)")
        hold = s.hold
        self.ladder = rungs(max_samples, max_steps)
        self.period_ms, self.high_ms, self.low_ms = period_ms, s.high * period_ms, s.low * period_ms
        self.base_hold, self.max_hold, self.hold = hold, s.max_hold, hold
        self.cooldown, self.probation, self.calm = s.cooldown, s.probation, s.calm
        self.level = len(self.ladder) - 1 if start is None else self._level_at_most(start)
        self.window = hold // 2               # frames judged before a raise (the newest ones)
        self._slow = bytearray(self.window)   # ring of "slower than low" flags, no allocation per frame
        self._slow_count = 0
        self._over = bytearray(10)            # the last ten frames: slower than high?
        self._over_count = 0
        self.frame = 0
        self.since_change = 0
        self.since_lower = self.cooldown + 1      # the first late frame acts at once
        self.last_raise_at = None
        # (frame, from N, to N, reason, from K, to K): the most recent CHANGE_HISTORY, for reports;
        # change_count counts all
        self.changes = deque(maxlen=CHANGE_HISTORY)
        self.change_count = 0

    @property
    def samples(self):
        return self.ladder[self.level][0]

    @property
    def steps(self):
        """Refinement steps a frame (K) at the current rung."""
        return self.ladder[self.level][1]

    def _level_at_most(self, n):
        """The highest rung with at most n samples (the most steps there)."""
        return max(i for i, (v, _) in enumerate(self.ladder) if v <= max(n, self.ladder[0][0]))

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
                cut = min(0.5, self.high_ms / frame_ms)     # at least one rung down (rungs can share an N)
                self._change(min(self.level - 1, self._level_at_most(int(self.samples * cut))), "late")
            self.since_lower = 0
        elif (self.level < len(self.ladder) - 1 and self._slow_count <= self.window // 10
              and self.since_change >= (self.base_hold if self._slow_count == 0 else self.hold)):
            self._change(self.level + 1, "slack")
            self.last_raise_at = self.frame
        if self.since_lower >= self.calm:
            self.hold = self.base_hold
        return self.samples

    def steer(self, pipeline, frame_ms):
        """Observe a frame of `pipeline` (anything with `samples` and `set_samples`, and with K steps on
        the ladder `set_refine_steps`) and pass a new N and K on."""
        before, steps = self.samples, self.steps
        n = self.observe(frame_ms, pipeline.samples)
        if n != before:
            pipeline.set_samples(n)
        if self.steps != steps:
            pipeline.set_refine_steps(self.steps)

    def _change(self, level, reason):
        """(frame, from N, to N, reason, from K, to K)"""
        (n0, k0), (n1, k1) = self.ladder[self.level], self.ladder[level]
        self.changes.append((self.frame, n0, n1, reason, k0, k1))
        self.change_count += 1
        self.level = level
        self.since_change = 0
