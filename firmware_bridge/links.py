"""The board's sources and its clock: a Link per configured device (opened by URL, drained each tick,
reopened with backoff when it fails), a Reader thread per link that stamps samples as they arrive,
and the Pacer that releases the model's ticks. edge run's Service holds them; edge calibrate and
edge profile use them too."""
import threading
import time
from collections import deque

from firmware_bridge.transports import DeviceUnavailable, TransportError, open_source, parse_url

REOPEN_AFTER_S = 0.25        # how often a failed device is retried
ERROR_REOPEN_S = 1.0         # a source that reports a fault (a CAN bus-off) this long is closed and reopened
MAX_DRAIN = 4096             # samples one tick takes from a link (a flood of valid ones cannot hold it)


class Pacer:
    """The model-rate clock of a loop: tick k is released at start + k / hz and is due by the next
    release. A tick whose deadline passed before it could start is skipped (counted), not run late,
    so a loop that fell behind resynchronises instead of bursting. `edge run` and `edge profile`
    pace with this one."""

    def __init__(self, hz, clock=time.monotonic, sleep=time.sleep):
        self.period, self.clock, self.sleep = 1.0 / hz, clock, sleep
        self.next, self.skipped = None, 0

    def start(self, at=None):
        """The first tick is released one period after `at` (default: now)."""
        self.next = (self.clock() if at is None else at) + self.period

    def wait(self, idle=None, nap=0.001):
        """Sleep until the next release, calling idle() between naps of at most `nap` seconds; return
        (release time, ticks skipped just now because their deadline had passed)."""
        skipped = 0
        while True:
            now = self.clock()
            if now >= self.next + self.period:        # this tick's deadline passed: skip it
                late = int((now - self.next) // self.period)
                skipped += late
                self.next += late * self.period
                continue
            if now >= self.next:
                release, self.next = self.next, self.next + self.period
                self.skipped += skipped
                return release, skipped
            if idle is not None:
                idle()
                now = self.clock()
            if now < self.next:
                self.sleep(min(nap, self.next - now))


class Link:
    """A source plus its reopen policy: a device that fails (unplugged) is retried, not fatal.

    required (the headset link): a URL the transport cannot use fails start-up (TransportError), but a
    device that is not there yet (DeviceUnavailable: a board that boots before the headset is plugged
    in) is waited for, retried like an unplug. Not required (a tracker): any failure is ridden through."""

    def __init__(self, url, opener=open_source, required=True):
        self.url, self.opener = url, opener
        self.down_since, self.reopens, self.start_error, self.error_since = None, 0, None, None
        self.past = {}                     # the counters of this link's earlier (closed) sources
        self.last_summary, self.last_status = None, None   # what a closed source last said of its link
        try:
            self.source = opener(url)
        except TransportError as e:
            if required and not isinstance(e, DeviceUnavailable):
                raise
            # Not there or not answering yet: ride through, say so, retry like an unplug.
            self.source, self.start_error, self.down_since = None, str(e), float("-inf")

    @property
    def device(self):
        """What the URL names, for a person: '/dev/ttyAMA0' from serial:///dev/ttyAMA0?role=headset."""
        try:
            _, netloc, path, _ = parse_url(self.url)
        except TransportError:
            return self.url
        return (netloc + path) or self.url

    def drain(self, clock, timeout=0.0):
        """Everything that has arrived, waiting up to `timeout` seconds for the first of it."""
        out = []
        if self.source is None:
            if clock() - self.down_since >= REOPEN_AFTER_S:
                try:
                    self.source = self.opener(self.url)
                    self.reopens += 1
                    self.down_since = None
                except TransportError:
                    self.down_since = clock()
            return out
        try:
            first = self.source.recv(timeout=timeout)
            if first is not None:
                out.append(first)
                while len(out) < MAX_DRAIN and (s := self.source.recv(timeout=0)) is not None:
                    out.append(s)
        except (TransportError, OSError):          # unplugged (EIO) or failed for good: retry later
            self.close()
            self.down_since = clock()
            return out
        if self.source.state == "error":           # e.g. CAN bus-off: reopen it if it does not recover
            self.error_since = clock() if self.error_since is None else self.error_since
            if clock() - self.error_since >= ERROR_REOPEN_S:
                self.close()
                self.down_since = clock() - REOPEN_AFTER_S     # reopened on the next drain
        else:
            self.error_since = None
        return out

    def stats(self):
        """This link's counters over all its sources, the closed ones included (they survive reconnects)."""
        live = self.source.stats if self.source is not None else {}
        return {k: self.past.get(k, 0) + live.get(k, 0) for k in set(self.past) | set(live)}

    def link_summary(self):
        """The source's own account of its link (a webxr headset: pairing, wrong codes, refused, frames),
        the live source's or, once closed, what it said last; None for sources that keep none."""
        return self.source.link_summary() if self.source is not None else self.last_summary

    def status_text(self):
        return self.source.status_text() if self.source is not None else self.last_status

    def close(self):
        if self.source is not None:
            for k, v in self.source.stats.items():
                if isinstance(v, (int, float)):
                    self.past[k] = self.past.get(k, 0) + v
            self.last_summary = self.source.link_summary()
            self.last_status = self.source.status_text()
            try:
                self.source.close()
            except OSError:
                pass
            self.source = None
            self.error_since = None


class Reader:
    """A link's reader thread, as python-can's Notifier feeds its Listeners: it waits in the source's
    recv, stamps each sample with the service's clock and queues it for the tick; reopening a port,
    re-initialising a device and recovering a bus happen here too, with the link's backoff. So a device
    whose read blocks (an I2C chip re-initialising, a slow bus) never holds the tick, which only takes
    what has arrived."""

    WAIT_S = 0.05               # longest wait in one recv: how soon the thread notices it should stop

    def __init__(self, link, clock, maxlen=MAX_DRAIN):
        self.link, self.clock = link, clock
        self.queue = deque(maxlen=maxlen)
        self.dropped = 0        # samples the tick did not take in time (the queue was full)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"edge reader {link.url}", daemon=True)
        self._thread.start()

    def _run(self):
        link, queue = self.link, self.queue
        while not self._stop.is_set():
            try:
                got = link.drain(self.clock, timeout=self.WAIT_S)
            except Exception as e:         # never let the thread die: count it, back off, go on
                link.past["errors"] = link.past.get("errors", 0) + 1
                link.last_error = f"{type(e).__name__}: {e}"
                got = []
                self._stop.wait(REOPEN_AFTER_S)
            now = self.clock()
            for sample in got:
                sample.received = now
                if len(queue) == queue.maxlen:
                    self.dropped += 1
                queue.append(sample)
            if link.source is None:        # down: the link retries every REOPEN_AFTER_S
                self._stop.wait(REOPEN_AFTER_S / 5)

    def take(self):
        """What arrived since the last call (oldest first)."""
        out, queue = [], self.queue
        while queue:
            out.append(queue.popleft())
        return out

    def stop(self):
        self._stop.set()
        self._thread.join(timeout=2.0)
