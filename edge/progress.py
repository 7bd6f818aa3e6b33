"""A dependency-free progress bar for long work (training, evaluation over many clips)."""
import sys
import time


class Progress:
    def __init__(self, total, desc="", stream=None, width=28):
        self.total, self.desc, self.width = max(int(total), 1), desc, width
        self.stream = stream or sys.stderr
        self.n, self.t0, self._last, self.postfix = 0, time.monotonic(), 0.0, ""
        self.enabled = hasattr(self.stream, "isatty") and self.stream.isatty()
        self._decile = 0     # off a terminal, a line per tenth of the way (counts may jump past one)

    def update(self, k=1, postfix=None):
        self.n += k
        if postfix is not None:
            self.postfix = postfix
        now = time.monotonic()
        if now - self._last > 0.2 or self.n >= self.total:
            self._last = now
            self._draw(now)

    def _draw(self, now):
        frac = min(self.n / self.total, 1.0)
        el = now - self.t0
        eta = el / frac - el if frac > 0 else 0
        bar = "#" * int(frac * self.width) + "-" * (self.width - int(frac * self.width))
        line = f"{self.desc} [{bar}] {self.n}/{self.total} {el:5.0f}s eta {eta:4.0f}s {self.postfix}"
        if self.enabled:
            self.stream.write("\r" + line[:160] + "\x1b[K")
        elif int(frac * 10) > self._decile:
            self._decile = int(frac * 10)
            self.stream.write(line[:160] + "\n")
        self.stream.flush()

    def close(self):
        if self.enabled:
            self.stream.write("\n")
            self.stream.flush()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
