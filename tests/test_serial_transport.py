"""The serial transport over a real pty pair: the test plays the device on the master side, the Source
opens the slave path through pyserial exactly as it would open /dev/ttyUSB0."""
import dataclasses
import os
import select
import time

import numpy as np
import pytest
import serial

from firmware_bridge.wire.messages import (
    FrameReader, encode_headset_pose, encode_tracker_samples,
)
from firmware_bridge.samples import HeadsetSample, TrackerSample
from firmware_bridge.transports import TransportError, open_source
from test_protocol import (
    assert_same_message, example_headset_pose, example_pose_frame, example_tracker_samples,
    random_pose_frame,
)


@pytest.fixture
def device():
    """(master fd the test writes device bytes into, slave path the Source opens)."""
    master, slave = os.openpty()
    yield master, os.ttyname(slave)
    os.close(master)
    os.close(slave)


@pytest.fixture
def source(device):
    _, path = device
    with open_source(f"serial://{path}?baud=921600") as src:
        yield src


def read_from_device(master, headset, timeout=2.0):
    """The messages in the bytes the board wrote, once at least one has arrived (the headset's view)."""
    messages = []
    deadline = time.monotonic() + timeout
    while not messages and time.monotonic() < deadline:
        if select.select([master], [], [], 0.05)[0]:
            messages += headset.feed(os.read(master, 4096))
    return messages


def receive(source, count, timeout=2.0):
    messages = []
    deadline = time.monotonic() + timeout
    while len(messages) < count and time.monotonic() < deadline:
        message = source.recv(timeout=0.1)
        if message is not None:
            messages.append(message)
    return messages


def test_tracker_samples_written_by_the_hub_arrive_as_tracker_samples(device, source):
    master, _ = device
    before = time.monotonic()
    os.write(master, encode_tracker_samples(example_tracker_samples(), seq=0))
    got = receive(source, 2)
    for message, want in zip(got, example_tracker_samples(), strict=True):
        assert_same_message(message, want)
        assert before <= message.received <= time.monotonic()
    assert source.stats["frames"] == 1 and source.stats["corrupt"] == 0


def test_headset_poses_arrive_as_headset_samples(device, source):
    master, _ = device
    sent = []
    for k in range(5):
        sample = example_headset_pose()
        sample.t += k / 90
        sample.head_pos = sample.head_pos + [0.01 * k, 0.0, 0.0]
        sent.append(sample)
        os.write(master, encode_headset_pose(sample, seq=k))
    for got, want in zip(receive(source, 5), sent, strict=True):
        assert_same_message(got, want)
    assert source.stats["missed"] == 0


def test_corrupt_bytes_between_frames_are_counted_and_skipped(device, source):
    master, _ = device
    frame = encode_headset_pose(example_headset_pose(), seq=0)
    noise = bytes(range(1, 60)) + b"\x00" + frame[:30] + b"\x00"     # garbage, then a cut-off frame
    os.write(master, frame + noise + encode_headset_pose(example_headset_pose(), seq=1))
    got = receive(source, 2)
    assert len(got) == 2
    assert source.recv(timeout=0.05) is None
    assert source.stats["corrupt"] == 2 and source.stats["frames"] == 2


def test_a_frame_split_across_writes_is_put_back_together(device, source):
    master, _ = device
    frame = encode_headset_pose(example_headset_pose(), seq=0)
    os.write(master, frame[:40])
    assert source.recv(timeout=0.05) is None
    os.write(master, frame[40:])
    [got] = receive(source, 1)
    assert_same_message(got, example_headset_pose())


def test_pose_frames_sent_by_the_board_arrive_intact_at_the_headset(device, source):
    master, _ = device
    headset = FrameReader()
    first = example_pose_frame()
    # The second frame's time follows on from the first's: a reader drops a lone jump of the clock.
    sent = [first, dataclasses.replace(random_pose_frame(np.random.default_rng(3)), t=first.t + 1 / 60)]
    for frame in sent:
        assert source.send_pose(frame)
        [got] = read_from_device(master, headset)
        assert_same_message(got, frame)
    assert headset.stats["missed"] == 0 and source.stats["sent"] == 2


def test_recv_returns_none_when_nothing_arrives_within_the_timeout(source):
    start = time.monotonic()
    assert source.recv(timeout=0) is None
    assert source.recv(timeout=0.1) is None
    assert 0.1 <= time.monotonic() - start < 1.0


def test_role_hub_accepts_tracker_samples_only(device):
    master, path = device
    with open_source(f"serial://{path}?role=hub") as hub:
        os.write(master, encode_headset_pose(example_headset_pose(), 0)
                 + encode_tracker_samples(example_tracker_samples()[:1], 0))
        [got] = receive(hub, 1)
        assert isinstance(got, TrackerSample)
        assert hub.recv(timeout=0.05) is None
        assert hub.stats["unexpected"] == 1 and hub.stats["corrupt"] == 0


def test_role_headset_accepts_headset_poses_only(device):
    master, path = device
    with open_source(f"serial://{path}?role=headset&baud=460800") as link:
        os.write(master, encode_tracker_samples(example_tracker_samples(), 0)
                 + encode_headset_pose(example_headset_pose(), 0))
        [got] = receive(link, 1)
        assert isinstance(got, HeadsetSample)
        assert link.stats["unexpected"] == 1


def test_tracker_names_from_the_config_name_the_samples(device):
    master, path = device
    names = {0: "waist", 2: "l_foot"}
    with open_source(f"serial://{path}?role=hub", tracker_names=names) as hub:
        os.write(master, encode_tracker_samples(example_tracker_samples(), 0))
        assert [s.tracker for s in receive(hub, 2)] == ["waist", "l_foot"]


def test_a_stalled_link_drops_the_frame_and_the_next_one_arrives_whole(device, source):
    master, _ = device
    frame = example_pose_frame()
    sent = 0
    while source.send_pose(frame):          # nobody reads the master: the pty buffer fills up
        sent += 1
        assert sent < 10_000
    assert source.stats["errors"] == 1
    headset = FrameReader()
    caught_up = []
    while select.select([master], [], [], 0.05)[0]:   # the headset catches up, ending on a cut-off frame
        caught_up += headset.feed(os.read(master, 65536))
    # The frame that timed out got through whole or cut off (pyserial can time out after writing it all).
    timed_out_frame_arrived = len(caught_up) - sent
    assert timed_out_frame_arrived in (0, 1)
    assert headset.stats["corrupt"] == 1 - timed_out_frame_arrived
    assert source.send_pose(frame)
    [got] = read_from_device(master, headset)
    assert_same_message(got, frame)


def test_after_a_cut_off_write_the_next_frame_still_arrives_whole(device, source, monkeypatch):
    master, _ = device
    write = source.port.write

    def write_half_then_time_out(data):
        write(data[:len(data) // 2])
        raise serial.SerialTimeoutException("Write timeout")

    monkeypatch.setattr(source.port, "write", write_half_then_time_out)
    assert not source.send_pose(example_pose_frame())
    monkeypatch.setattr(source.port, "write", write)
    assert source.send_pose(example_pose_frame())      # starts with a 0x00 that ends the cut-off frame
    headset = FrameReader()
    [got] = read_from_device(master, headset)
    assert_same_message(got, example_pose_frame())
    assert headset.stats["corrupt"] == 1 and source.stats["errors"] == 1


def test_port_that_cannot_be_opened_raises_transport_error_naming_it():
    with pytest.raises(TransportError, match="/dev/edgepose-no-such-port"):
        open_source("serial:///dev/edgepose-no-such-port?baud=460800")


def test_port_already_open_elsewhere_raises_transport_error(device, source):
    _, path = device
    with pytest.raises(TransportError, match="cannot open serial port"):
        open_source(f"serial://{path}")


@pytest.mark.parametrize("url, complaint", [
    ("serial://", "names no port"),
    ("serial:///dev/ttyUSB0?baud=fast", "baud"),
    ("serial:///dev/ttyUSB0?role=tracker", "role"),
])
def test_bad_serial_urls_say_what_is_wrong(url, complaint):
    with pytest.raises(TransportError, match=complaint):
        open_source(url)
