"""The `can` scheme: IMU tracker nodes on a CAN bus, through python-can 4.x.

    source = open_source("can://socketcan/can0?nodes=1:waist,2:l_foot,3:r_foot")
    source = open_source("can://virtual/bus0")          # python-can's in-process bus (tests, simulator)
    sample = source.recv(timeout=0.02)                  # TrackerSample or None

URL: `can://INTERFACE/CHANNEL?nodes=ID:NAME,...&bitrate=BPS` -> `can.Bus(interface=INTERFACE,
channel=CHANNEL, bitrate=BPS)`. `nodes` maps node ids to tracker names; without it every node is
accepted and named "node<ID>"; with it, frames from other nodes count as unknown. `bitrate` is only
needed by interfaces that set it themselves (SocketCAN takes it from `ip link`).

The frames and their decoding: firmware_bridge.wire.can_frames (and can.md beside it).
"""
import time

import can

from firmware_bridge.transports.base import Source, TransportError, id_names
from firmware_bridge.wire.can_frames import MAX_NODE_ID, TrackerFrameDecoder, new_stats

FRAMES_PER_CALL = 64               # one recv reads what is queued, but not an endless flood

BUS_HINTS = {
    "socketcan": "bring the interface up first: `sudo ip link set {channel} up type can bitrate 1000000` "
                 "(a virtual one: `sudo modprobe vcan && sudo ip link add dev {channel} type vcan && "
                 "sudo ip link set {channel} up`)",
    "udp_multicast": "python-can's udp_multicast interface needs msgpack: pip install msgpack",
}


# ---- URL parts ------------------------------------------------------------------------------------

def parse_node_map(text):
    """'1:waist,2:l_foot' -> {1: 'waist', 2: 'l_foot'} (ids decimal or 0x hex); '' -> {}."""
    return id_names(text, range(1, MAX_NODE_ID + 1), "nodes=1:waist,2:l_foot")


def tracker_names(parsed):
    return list(parse_node_map(parsed[3].get("nodes", "")).values())


def bus_arguments(netloc, path, query):
    """URL parts -> keyword arguments for can.Bus."""
    channel = path.strip("/")
    if not netloc or not channel:
        raise TransportError("a CAN URL names the python-can interface and channel: can://virtual/bus0, "
                             "can://socketcan/can0, can://udp_multicast/239.74.163.2")
    arguments = {"interface": netloc, "channel": channel}
    if "bitrate" in query:
        arguments["bitrate"] = int(query["bitrate"])
    return arguments


def open_bus(interface, channel, **options):
    """can.Bus(...), with errors that say what to do."""
    try:
        return can.Bus(interface=interface, channel=channel, **options)
    except (can.CanError, OSError, ValueError, ImportError) as error:
        hint = BUS_HINTS.get(interface, "see python-can's list of interfaces and what each needs")
        raise TransportError(f"cannot open CAN interface {interface!r} channel {channel!r} ({error}): "
                             f"{hint.format(channel=channel)}") from error


def open(url, parsed, bus=None, **bus_options):
    """Open the CAN source the URL names. `bus`: an open python-can bus to use instead (the source
    does not shut it down); `bus_options` go to can.Bus."""
    _, netloc, path, query = parsed
    node_names = parse_node_map(query.get("nodes", ""))
    owns_bus = bus is None
    if owns_bus:
        bus = open_bus(**bus_arguments(netloc, path, query), **bus_options)
    return CanSource(bus, node_names, url=url, owns_bus=owns_bus)


# ---- the source -----------------------------------------------------------------------------------

class CanSource(Source):
    """TrackerSamples from the tracker nodes on one python-can bus. `state` is "error" while the bus
    reports errors (a bus-off shows here) and "active" again once frames arrive."""

    def __init__(self, bus, node_names=None, *, url="", owns_bus=True, **decoder_options):
        super().__init__()
        self.stats = new_stats()
        self.url = url
        self.bus = bus
        self.owns_bus = owns_bus
        self.last_error = None
        self._bus_error = False
        self.decoder = TrackerFrameDecoder(node_names, stats=self.stats, **decoder_options)

    def _recv_internal(self, timeout):
        """Wait up to `timeout` for a frame, then read the queued ones until a sample completes."""
        wait = timeout
        for _ in range(FRAMES_PER_CALL):
            try:
                msg = self.bus.recv(wait)
            except can.CanError as error:
                self._count_bus_error(error, timeout)
                return None
            if msg is None:
                return None
            if not msg.is_error_frame:
                self._bus_error = False
            sample = self.decoder.feed(msg, received=time.monotonic())
            if sample is not None:
                return sample
            wait = 0.0
        return None

    @property
    def state(self):
        if self._closed:
            return "closed"
        try:
            bus_state = self.bus.state
        except (NotImplementedError, can.CanError, OSError):
            bus_state = None
        if self._bus_error or bus_state == can.BusState.ERROR:
            return "error"
        return "active"

    def _close_internal(self):
        if self.owns_bus:
            self.bus.shutdown()
            self.owns_bus = False

    def _count_bus_error(self, error, timeout):
        self.stats["errors"] += 1
        self._bus_error = True
        self.last_error = f"{type(error).__name__}: {error}"
        # Do not spin on a bus that keeps failing (an interface that went down).
        time.sleep(0.01 if timeout is None else min(0.01, timeout))
