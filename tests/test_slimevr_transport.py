"""slimevr:// on real UDP sockets on loopback: emulated SlimeVR trackers (firmware_bridge.wire.slimevr's
TrackerEncoder, built as the firmware builds its packets) do the handshake and stream; the board's
source answers as the SlimeVR server does and yields the configured sensors as TrackerSamples."""
import socket
import time

import numpy as np
import pytest

from edge import quat
from firmware_bridge import config as config_mod
from firmware_bridge.wire import slimevr as w
from firmware_bridge.transports import open_source
from firmware_bridge.transports.base import TransportError
from firmware_bridge.transports.slimevr import AXES_OFFSET

MAC, OTHER = "02:ed:9e:00:00:01", "02:ed:9e:00:00:02"


class EmulatedTracker:
    """A SlimeVR tracker on a UDP socket of its own."""

    def __init__(self, server, mac=MAC):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(1.0)
        self.server, self.enc = server, w.TrackerEncoder(mac)

    def send(self, data):
        self.sock.sendto(data, self.server)

    def replies(self, seconds=0.3):
        out, end = [], time.monotonic() + seconds
        self.sock.settimeout(0.02)
        while time.monotonic() < end:
            try:
                out.append(self.sock.recv(2048))
            except socket.timeout:
                pass
        return out


def drain(src, seconds=0.2):
    got, end = [], time.monotonic() + seconds
    while time.monotonic() < end:
        s = src.recv(timeout=0.02)
        if s is not None:
            got.append(s)
    return got


@pytest.fixture
def source():
    src = open_source(f"slimevr://127.0.0.1:0?trackers={MAC}/0:l_shin,{MAC}/1:r_shin")
    yield src
    src.close()


def test_a_tracker_is_answered_like_the_slimevr_server_and_its_sensors_arrive_by_name(source):
    t = EmulatedTracker(source.address)
    t.send(t.enc.handshake())
    drain(source, 0.05)
    assert w.HANDSHAKE_REPLY in t.replies(0.1)                     # what the firmware waits for
    t.send(t.enc.sensor_info(0))
    q = quat.from_axis_angle(np.array([0.0, 0.0, 1.0]), np.array(0.3))
    t.send(t.enc.bundle([(0, q), (1, q)]))
    t.send(t.enc.rotation(1, q))
    t.send(t.enc.battery(3.9, 0.8))
    got = drain(source)
    assert [s.tracker for s in got] == ["l_shin", "r_shin", "r_shin"]
    np.testing.assert_allclose(got[0].quat, quat.mul(AXES_OFFSET, q), atol=1e-6)    # Z-up -> Y-up
    info = source.trackers()[MAC]
    assert info["sensors"] == {0: 1} and info["battery"] == pytest.approx(0.8) and info["in_use"]
    drain(source, 0.7)                                             # the board keeps reading for 0.7 s
    replies = t.replies(0.1)
    assert w.sensor_info_ack(0, 1) in replies                      # SENSOR_INFO acknowledged
    assert replies.count(w.heartbeat()) >= 1                       # kept alive every 0.5 s


def test_duplicates_old_packets_and_garbage_are_dropped_and_counted(source):
    t = EmulatedTracker(source.address)
    t.send(t.enc.handshake())
    q = np.array([1.0, 0, 0, 0])
    late = t.enc.rotation(0, q)
    fresh = t.enc.rotation(0, q)
    t.send(fresh)
    t.send(fresh)                       # a duplicate
    t.send(late)                        # older than what came
    t.send(b"\x00\x00\x00\x11garbage")
    got = drain(source)
    assert len(got) == 1
    assert source.stats["dropped_old"] == 2 and source.stats["corrupt"] == 1


def test_one_packet_numbered_far_ahead_is_dropped_and_the_tracker_keeps_streaming(source):
    """A datagram whose packet number was damaged (a bit flipped high: edge soak's bit errors found it)
    must not make every later packet "old"; a jump the next packet follows on from is believed."""
    from firmware_bridge.transports.slimevr import NUMBER_STEP_MAX
    t = EmulatedTracker(source.address)
    t.send(t.enc.handshake())
    q = np.array([1.0, 0, 0, 0])
    for _ in range(3):
        t.send(t.enc.rotation(0, q))
    damaged = bytearray(t.enc.rotation(0, q))
    damaged[4] ^= 0x40                          # the u64 packet number's top byte
    t.send(bytes(damaged))
    for _ in range(3):
        t.send(t.enc.rotation(0, q))
    assert len(drain(source)) == 6 and source.stats["corrupt_number"] == 1
    t.enc.number += 5 * NUMBER_STEP_MAX         # a real jump (the firmware's counter moved on): confirmed
    t.send(t.enc.rotation(0, q))
    t.send(t.enc.rotation(0, q))
    assert len(drain(source)) == 1 and source.stats["corrupt_number"] == 2
    # the first packet after a handshake has nothing to be checked against: a damaged one is believed,
    # and the true numbers, far behind it, win the stream back from the second on
    t.send(t.enc.handshake())
    damaged = bytearray(t.enc.rotation(0, q))
    damaged[5] ^= 0x01
    t.send(bytes(damaged))
    for _ in range(4):
        t.send(t.enc.rotation(0, q))
    assert len(drain(source)) == 1 + 3 and source.stats["corrupt_number"] == 3


def test_a_restarted_tracker_handshakes_again_and_is_back_with_numbers_from_zero(source):
    t = EmulatedTracker(source.address)
    t.send(t.enc.handshake())
    for _ in range(5):
        t.send(t.enc.rotation(0, np.array([1.0, 0, 0, 0])))
    assert len(drain(source)) == 5
    t2 = EmulatedTracker(source.address)                  # rebooted: new socket, same MAC, numbers restart
    t2.send(t2.enc.handshake())
    t2.send(t2.enc.rotation(0, np.array([1.0, 0, 0, 0])))
    assert len(drain(source)) == 1 and source.trackers()[MAC]["sensors"] == {}
    assert source.by_mac[MAC].handshakes == 2


def test_only_configured_trackers_feed_the_model_and_accept_any_answers_the_rest():
    strict = open_source(f"slimevr://127.0.0.1:0?trackers={MAC}/0:waist")
    loose = open_source(f"slimevr://127.0.0.1:0?trackers={MAC}/0:waist&accept=any")
    try:
        for src, answered in ((strict, False), (loose, True)):
            t = EmulatedTracker(src.address, OTHER)
            t.send(t.enc.handshake())
            t.send(t.enc.rotation(0, np.array([1.0, 0, 0, 0])))
            assert drain(src) == []
            assert (w.HANDSHAKE_REPLY in t.replies(0.1)) == answered
            assert src.trackers()[OTHER]["in_use"] is False
    finally:
        strict.close()
        loose.close()


def test_bad_urls_and_names_fail_at_start_with_the_fix():
    with pytest.raises(TransportError, match="MAC/SENSOR:NAME"):
        open_source("slimevr://127.0.0.1:0?trackers=02:ed:9e:00:00:01:l_shin")
    with pytest.raises(TransportError, match="HOST:PORT"):
        open_source("slimevr://localhost")
    cfg = config_mod.from_dict({"headset": {"url": "serial:///dev/null"},
                                "trackers": [{"url": f"slimevr://0.0.0.0:6969?trackers={MAC}/0:l_shin,{MAC}/1:r_shin"}]})
    assert cfg.tracker_names == ["l_shin", "r_shin"]
    with pytest.raises(config_mod.ConfigError, match="unknown tracker name 'knee'"):
        config_mod.from_dict({"headset": {"url": "serial:///dev/null"},
                              "trackers": [{"url": f"slimevr://0.0.0.0:6969?trackers={MAC}/0:knee"}]})
