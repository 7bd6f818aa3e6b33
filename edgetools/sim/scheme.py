"""The `sim` scheme: sources on the simulator's devices, opened by URL like any other.

    sim://i2c/waist-puck?tracker=waist&rate=100      a BNO055Source on the bench's register-level fake
    sim://slimevr/trackers?trackers=MAC/0:l_foot      a SlimeVRSource on loopback, on the bench's clock
    sim://feed/profile-headset                        samples the bench queues, as decoded (edge profile);
    sim://feed/profile-waist?tracker=waist            pose frames sent to it are encoded and counted

The simulator puts its devices on the bench (`BENCH[name] = BenchDevice(...)`) before the service
starts; the path names one. The real transport code reads them (the i2c driver with its retries and
backoff, the SlimeVR server side), with the simulator's clock so `--speed max` runs on simulated time.
Registered with the transports when this module is imported.
"""
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Callable

from firmware_bridge.transports import i2c, slimevr
from firmware_bridge.transports.base import Source, TransportError, register_scheme
from firmware_bridge.wire.messages import PoseEncoder

BENCH = {}


@dataclass
class BenchDevice:
    """What a sim:// source opens: an SMBus-like `bus` (I2C), the simulator's clock and sleep, and
    `on_open(source)`, called with each source opened on it (the simulator learns the port it got)."""
    bus: Any = None
    clock: Callable = time.monotonic
    sleep: Callable = time.sleep
    on_open: Callable = None
    queue: deque = field(default_factory=deque)      # sim://feed: the samples it will yield


class FeedSource(Source):
    """sim://feed: the samples the bench queued, in order, as a transport would have decoded them;
    and the pose stream's far end (send_pose encodes each frame with the real encoder)."""

    def __init__(self, url, device):
        super().__init__(device.clock)
        self.url, self.queue = url, device.queue
        self.stats["sent"] = self.stats["sent_bytes"] = 0
        self._seq = 0
        self._encoder = None

    def _recv_internal(self, timeout):
        if self.queue:
            self.stats["frames"] += 1
            return self.queue.popleft()
        return None

    def send_pose(self, frame):
        if self._encoder is None:
            self._encoder = PoseEncoder()
        data = self._encoder.encode(frame, self._seq)
        self._seq = (self._seq + 1) & 0xFFFF
        self.stats["sent"] += 1
        self.stats["sent_bytes"] += len(data)
        return True


def _device(url, path):
    name = path.strip("/")
    if name not in BENCH:
        raise TransportError(f"{url!r}: no simulated device {name!r} on the bench (there are: "
                             f"{', '.join(sorted(BENCH)) or 'none'})")
    return BENCH[name]


def tracker_names(parsed):
    kind, query = parsed[1], parsed[3]
    if kind == "feed":
        return [query["tracker"]] if "tracker" in query else []
    return (i2c.tracker_names if kind == "i2c" else slimevr.tracker_names)(parsed)


def open(url, parsed, **_):
    _, kind, path, query = parsed
    device = _device(url, path)
    if kind == "i2c":
        source = i2c.open_on_bus(url, ("i2c", "sim", "", query), device.bus, clock=device.clock, sleep=device.sleep)
    elif kind == "slimevr":
        source = slimevr.open(url, ("slimevr", "127.0.0.1:0", "", query), clock=device.clock)
    elif kind == "feed":
        source = FeedSource(url, device)
    else:
        raise TransportError(f"{url!r}: simulated devices are sim://i2c/NAME, sim://slimevr/NAME or sim://feed/NAME")
    if device.on_open is not None:
        device.on_open(source)
    return source


register_scheme("sim", __name__)
