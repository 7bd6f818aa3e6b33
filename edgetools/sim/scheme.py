"""The `sim` scheme: sources on the simulator's devices, opened by URL like any other.

    sim://i2c/waist-puck?tracker=waist&rate=100      a BNO055Source on the bench's register-level fake
    sim://slimevr/trackers?trackers=MAC/0:l_foot      a SlimeVRSource on loopback, on the bench's clock

The simulator puts its devices on the bench (`BENCH[name] = BenchDevice(...)`) before the service
starts; the path names one. The real transport code reads them (the i2c driver with its retries and
backoff, the SlimeVR server side), with the simulator's clock so `--speed max` runs on simulated time.
Registered with the transports when this module is imported.
"""
import time
from dataclasses import dataclass
from typing import Any, Callable

from firmware_bridge.transports import i2c, slimevr
from firmware_bridge.transports.base import TransportError, register_scheme

BENCH = {}


@dataclass
class BenchDevice:
    """What a sim:// source opens: an SMBus-like `bus` (I2C), the simulator's clock and sleep, and
    `on_open(source)`, called with each source opened on it (the simulator learns the port it got)."""
    bus: Any = None
    clock: Callable = time.monotonic
    sleep: Callable = time.sleep
    on_open: Callable = None


def _device(url, path):
    name = path.strip("/")
    if name not in BENCH:
        raise TransportError(f"{url!r}: no simulated device {name!r} on the bench (there are: "
                             f"{', '.join(sorted(BENCH)) or 'none'})")
    return BENCH[name]


def tracker_names(parsed):
    kind = parsed[1]
    return (i2c.tracker_names if kind == "i2c" else slimevr.tracker_names)(parsed)


def open(url, parsed, **_):
    _, kind, path, query = parsed
    device = _device(url, path)
    if kind == "i2c":
        source = i2c.open_on_bus(url, ("i2c", "sim", "", query), device.bus, clock=device.clock, sleep=device.sleep)
    elif kind == "slimevr":
        source = slimevr.open(url, ("slimevr", "127.0.0.1:0", "", query), clock=device.clock)
    else:
        raise TransportError(f"{url!r}: simulated devices are sim://i2c/NAME or sim://slimevr/NAME")
    if device.on_open is not None:
        device.on_open(source)
    return source


register_scheme("sim", __name__)
