"""Going down without losing anything: a stop asked for by a signal, and files replaced whole.

systemd stops a service with SIGTERM (then SIGKILL after TimeoutStopSec), a person with Ctrl-C. Either
one, by default, can end the process between two writes: a BVH whose header still says 0 frames, a
session recording never saved, a calibration file cut in half. StopSignals turns both signals into a
request that the loop reads at its next tick, so the loop ends the way it ends at its time limit (the
outputs flushed and closed, the summary written); a second signal while it shuts down is ignored, so
the clean-up itself is never cut short. replace_whole writes a file beside its destination and renames
it over it: a reader (or the next start) finds the old file or the new one, never part of one.
"""
import os
import signal
import threading
from contextlib import contextmanager
from pathlib import Path


class StopSignals:
    """SIGTERM and SIGINT as a request to stop: `requested()` is true once one came, and `signal_name`
    says which. A context manager: the previous handlers come back on exit. Outside the main thread
    (where Python allows no handlers) it installs nothing and never reports a request."""

    SIGNALS = (signal.SIGTERM, signal.SIGINT)

    def __init__(self):
        self.signal_name = None
        self._previous = {}

    def _handle(self, signum, _frame):
        if self.signal_name is None:
            self.signal_name = signal.Signals(signum).name

    def requested(self):
        return self.signal_name is not None

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            self._previous = {s: signal.signal(s, self._handle) for s in self.SIGNALS}
        return self

    def __exit__(self, *exc):
        for s, handler in self._previous.items():
            signal.signal(s, handler)
        self._previous = {}


@contextmanager
def replace_whole(path):
    """Yield a temporary path beside `path` to write; when the block ends without an error, the file is
    synced and renamed over `path` (atomic on one file system); on an error it is removed and `path`
    keeps what it had. The temporary name keeps the suffix, for writers that add or check one."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.tmp{path.suffix}")
    try:
        yield tmp
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
