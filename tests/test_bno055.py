"""The BNO055 driver and the i2c transport against the register-level fake (no /dev/i2c here).

A ManualClock drives both the fake and the driver, so settle times, boot waits and backoff cost no
real time.
"""
import errno
from pathlib import Path

import numpy as np
import pytest

from firmware_bridge.transports import bno055
from firmware_bridge.transports.bno055 import Mode, Reg
from firmware_bridge.samples import TrackerSample
from edgetools.sim.bno055_fake import ChipBehaviour, FakeBNO055, ManualClock, motion_from_arrays
from firmware_bridge.transports import TransportError, open_source
from firmware_bridge.transports.i2c import Recovery, backoff_delay, next_poll_time

ADDRESS = 0x28


@pytest.fixture
def clock():
    return ManualClock(start=100.0)


def make_fake(clock, motion=None, **behaviour):
    """A fake on the manual clock; `behaviour`: ChipBehaviour's fields."""
    return FakeBNO055(*(() if motion is None else (motion,)), clock=clock, sleep=clock.sleep,
                      behaviour=ChipBehaviour(**behaviour))


def open_fake(fake, clock, url="i2c://1/0x28?tracker=waist&rate=100", **options):
    return open_source(url, bus=fake, clock=clock, sleep=clock.sleep, **options)


def samples(source, count, timeout=0.1):
    received = [source.recv(timeout=timeout) for _ in range(count)]
    return [s for s in received if s is not None]


def random_unit_quaternion(rng):
    q = rng.normal(size=4)
    return q / np.linalg.norm(q)


def writes_to(fake, register):
    return [(i, access) for i, access in enumerate(fake.log) if access.operation == "write" and access.register == register]


# ---- set-up ---------------------------------------------------------------------------------------

def test_open_switches_to_config_then_ndof_waiting_the_datasheet_settle_times(clock):
    fake = make_fake(clock)
    open_fake(fake, clock)
    log = list(fake.log)
    mode_writes = writes_to(fake, Reg.OPR_MODE)
    assert [access.detail for _, access in mode_writes] == [Mode.CONFIG, Mode.NDOF]
    for index, access in mode_writes:
        next_access = log[index + 1]
        assert next_access.t - access.t >= bno055.switch_time(access.detail) - 1e-12
    assert all(access.ok for access in log)
    assert fake.mode == Mode.NDOF
    assert fake.ignored_writes == []          # PWR_MODE and UNIT_SEL were written in CONFIG mode


def test_fake_refuses_a_driver_that_does_not_wait_for_a_mode_switch(clock):
    fake = make_fake(clock)
    fake.write_byte_data(ADDRESS, Reg.OPR_MODE, Mode.NDOF)
    clock.sleep(0.006)
    with pytest.raises(OSError) as nack:
        fake.read_byte_data(ADDRESS, Reg.SYS_STATUS)
    assert nack.value.errno == errno.EREMOTEIO
    clock.sleep(0.001)
    assert fake.read_byte_data(ADDRESS, Reg.SYS_STATUS) == bno055.SYS_STATUS_FUSION_RUNNING

    fake.write_byte_data(ADDRESS, Reg.OPR_MODE, Mode.CONFIG)
    clock.sleep(0.018)
    with pytest.raises(OSError):
        fake.read_byte_data(ADDRESS, Reg.SYS_STATUS)
    clock.sleep(0.001)
    assert fake.read_byte_data(ADDRESS, Reg.SYS_STATUS) == bno055.SYS_STATUS_IDLE


def test_stale_switch_model_answers_with_zeros_until_fusion_starts(clock):
    fake = make_fake(clock, during_switch="stale")
    fake.write_byte_data(ADDRESS, Reg.OPR_MODE, Mode.NDOF)
    assert bytes(fake.read_i2c_block_data(ADDRESS, Reg.QUA_DATA, 8)) == bytes(8)
    clock.sleep(bno055.SWITCH_FROM_CONFIG_S)
    assert bno055.decode_quaternion(fake.read_i2c_block_data(ADDRESS, Reg.QUA_DATA, 8))[0] == 1.0


def test_open_selects_register_page_0_before_reading_the_chip_id(clock):
    fake = make_fake(clock)
    fake.write_byte_data(ADDRESS, Reg.PAGE_ID, 1)
    assert fake.read_byte_data(ADDRESS, Reg.CHIP_ID) != bno055.CHIP_ID
    open_fake(fake, clock)
    assert fake.mode == Mode.NDOF


def test_chip_id_mismatch_raises_a_clear_error(clock):
    fake = make_fake(clock, chip_id=0x42)
    with pytest.raises(TransportError, match=r"0x42.*0xa0"):
        open_fake(fake, clock)


def test_no_chip_at_the_address_names_the_address_and_i2cdetect(clock):
    fake = make_fake(clock)                    # answers at 0x28 only
    with pytest.raises(TransportError, match=r"0x29.*i2cdetect -y 1"):
        open_fake(fake, clock, url="i2c://1/0x29")


def test_open_retries_a_set_up_interrupted_by_a_bus_error(clock):
    fake = make_fake(clock)
    fake.fail_between(0.015, 0.025)                      # during the CONFIG settle wait: the NDOF write fails
    source = open_fake(fake, clock)
    assert fake.mode == Mode.NDOF
    assert source.recv(timeout=0.1) is not None


def test_open_waits_for_a_chip_still_in_its_power_on_reset(clock):
    fake = make_fake(clock, boot_seconds=0.4)
    start = clock()
    source = open_fake(fake, clock)
    assert clock() - start >= 0.4
    assert source.recv(timeout=0.1) is not None


def test_missing_i2c_device_says_how_to_enable_i2c():
    if Path("/dev/i2c-97").exists():
        pytest.skip("this machine has a /dev/i2c-97")
    with pytest.raises(TransportError, match="raspi-config"):
        open_source("i2c://97/0x28")


@pytest.mark.parametrize("url, complaint", [
    ("i2c://1/0x30", "0x28"),
    ("i2c://one/0x28", "bus number"),
    ("i2c://1/0x28?rate=250", "rate"),
    ("i2c://1/0x28?rate=fast", "rate"),
])
def test_bad_urls_are_refused_with_what_to_write(url, complaint):
    with pytest.raises(TransportError, match=complaint):
        open_source(url, bus=object())


def test_setup_selects_metres_per_second_squared_even_if_mg_was_set(clock):
    fake = make_fake(clock, motion=lambda t: (np.array([1.0, 0, 0, 0]), np.array([0.0, 0.0, 9.80665])))
    fake.write_byte_data(ADDRESS, Reg.UNIT_SEL, 0x81)             # mg, Android orientation
    sample = open_fake(fake, clock).recv(timeout=0.1)
    assert fake.read_byte_data(ADDRESS, Reg.UNIT_SEL) == 0x80     # only the accel unit bit changed
    assert sample.accel == pytest.approx([0.0, 0.0, 9.81])


# ---- data ---------------------------------------------------------------------------------------

def test_register_scaling_follows_the_datasheet():
    assert bno055.decode_quaternion(bytes([0x00, 0x40, 0, 0, 0, 0, 0, 0])).tolist() == [1.0, 0.0, 0.0, 0.0]
    assert bno055.decode_quaternion(bytes([0, 0, 0x00, 0xC0, 0, 0, 0, 0])).tolist() == [0.0, -1.0, 0.0, 0.0]
    assert bno055.decode_acceleration(bytes([100, 0, 0x9C, 0xFF, 0xE8, 0x03])).tolist() == [1.0, -1.0, 10.0]
    assert bno055.decode_acceleration(bytes([0xE8, 0x03, 0, 0, 0, 0]), accel_in_mg=True)[0] == pytest.approx(9.80665)


def test_quaternion_and_linear_acceleration_round_trip_through_the_registers(clock):
    rng = np.random.default_rng(7)
    quats = np.array([random_unit_quaternion(rng) for _ in range(50)])
    accels = rng.uniform(-30, 30, size=(50, 3))
    fake = make_fake(clock, motion=motion_from_arrays(quats, accels, rate=100.0))
    source = open_fake(fake, clock)
    for _ in range(20):
        sample = source.recv(timeout=0.1)
        assert isinstance(sample, TrackerSample)
        frame = int(np.floor(fake.elapsed() * 100.0 + 1e-9)) % 50
        assert sample.tracker == "waist"
        assert sample.quat == pytest.approx(quats[frame], abs=2e-4)
        assert np.linalg.norm(sample.quat) == pytest.approx(1.0)
        assert sample.accel == pytest.approx(accels[frame], abs=0.005 + 1e-9)
        assert sample.t == sample.received == clock()
        levels, sys_status, sys_err = bno055.unpack_status(sample.status)
        assert (sys_status, sys_err) == (bno055.SYS_STATUS_FUSION_RUNNING, 0)


def test_each_sample_is_two_burst_reads_with_the_quaternion_in_one_piece(clock):
    fake = make_fake(clock)
    source = open_fake(fake, clock)
    fake.log.clear()
    source.recv(timeout=0.1)
    assert [(a.operation, a.register, a.detail) for a in fake.log] == [
        ("block_read", Reg.QUA_DATA, 14),              # quaternion W..Z and linear acceleration X..Z
        ("block_read", Reg.CALIB_STAT, 6),             # CALIB_STAT .. SYS_ERR
    ]


def test_data_registers_are_zero_outside_the_fusion_modes(clock):
    fake = make_fake(clock, motion=lambda t: (np.array([0.0, 1.0, 0, 0]), np.array([1.0, 2.0, 3.0])))
    assert bytes(fake.read_i2c_block_data(ADDRESS, Reg.QUA_DATA, 14)) == bytes(14)      # CONFIG after reset
    fake.write_byte_data(ADDRESS, Reg.OPR_MODE, Mode.ACCONLY)
    clock.sleep(0.01)
    assert bytes(fake.read_i2c_block_data(ADDRESS, Reg.QUA_DATA, 14)) == bytes(14)
    assert fake.read_byte_data(ADDRESS, Reg.SYS_STATUS) == bno055.SYS_STATUS_RUNNING_NO_FUSION
    fake.write_byte_data(ADDRESS, Reg.OPR_MODE, Mode.NDOF)
    clock.sleep(0.01)
    assert bytes(fake.read_i2c_block_data(ADDRESS, Reg.QUA_DATA, 14)) != bytes(14)
    fake.write_byte_data(ADDRESS, Reg.OPR_MODE, Mode.CONFIG)
    clock.sleep(0.02)
    assert bytes(fake.read_i2c_block_data(ADDRESS, Reg.QUA_DATA, 14)) == bytes(14)


def test_fake_ignores_configuration_writes_outside_config_mode(clock):
    fake = make_fake(clock)
    open_fake(fake, clock)
    fake.write_byte_data(ADDRESS, Reg.UNIT_SEL, 0x81)
    assert fake.read_byte_data(ADDRESS, Reg.UNIT_SEL) == 0x80
    assert fake.ignored_writes == [(Reg.UNIT_SEL, 0x81)]


def test_fusion_output_changes_at_100_hz_however_fast_it_is_polled(clock):
    fake = make_fake(clock, motion=lambda t: (np.array([1.0, 0, 0, 0]), np.array([t, 0.0, 0.0])))
    open_fake(fake, clock)
    first = fake.read_i2c_block_data(ADDRESS, Reg.LIA_DATA, 6)
    clock.sleep(0.002)
    assert fake.read_i2c_block_data(ADDRESS, Reg.LIA_DATA, 6) == first
    clock.sleep(0.010)
    assert fake.read_i2c_block_data(ADDRESS, Reg.LIA_DATA, 6) != first


def test_calibration_status_rises_over_time_to_fully_calibrated(clock):
    fake = make_fake(clock, calibration_seconds=(1.0, 3.0, 2.0))
    source = open_fake(fake, clock, url="i2c://1/0x28?rate=20")
    levels = [bno055.unpack_status(s.status)[0] for s in samples(source, 100)]
    assert levels[0] == (0, 0, 0, 0)
    for field in range(4):
        series = [level[field] for level in levels]
        assert series == sorted(series)
    assert levels[-1] == (3, 3, 3, 3)
    assert [level.sys for level in levels].index(3) >= [level.acc for level in levels].index(3)


def test_recv_polls_at_the_configured_rate(clock):
    source = open_fake(make_fake(clock), clock, url="i2c://1/0x28?rate=50")
    times = [s.t for s in samples(source, 10)]
    assert np.diff(times) == pytest.approx(np.full(9, 0.02))


def test_recv_returns_none_when_the_timeout_ends_before_the_next_poll(clock):
    source = open_fake(make_fake(clock), clock, url="i2c://1/0x28?rate=10")
    assert source.recv(timeout=0.0) is not None
    start = clock()
    assert source.recv(timeout=0.03) is None
    assert clock() - start == pytest.approx(0.03)


# ---- faults -------------------------------------------------------------------------------------

def test_recv_recovers_from_bus_errors_and_counts_them(clock):
    fake = make_fake(clock)
    source = open_fake(fake, clock)
    assert len(samples(source, 5)) == 5
    fake.fail_next(6, errno.EIO)
    assert len(samples(source, 30, timeout=1.0)) == 30      # every recv got a sample once errors stopped
    assert source.stats["errors"] == 6
    assert source.stats["reinits"] >= 1               # three failures in a row set the chip up again
    assert "Errno 5" in source.last_error
    assert fake.mode == Mode.NDOF


def test_retries_back_off_exponentially():
    assert [backoff_delay(n, first=0.01, cap=1.0) for n in range(1, 9)] == pytest.approx(
        [0.01, 0.02, 0.04, 0.08, 0.16, 0.32, 0.64, 1.0])
    assert backoff_delay(10_000) == 1.0


def test_failed_reads_are_retried_with_growing_gaps(clock):
    fake = make_fake(clock)
    source = open_fake(fake, clock, url="i2c://1/0x28?rate=100", recovery=Recovery(reinit_after=100))
    source.recv(timeout=0.1)
    fake.fail_next(5)
    assert source.recv(timeout=2.0) is not None
    failed = [access.t for access in fake.log if not access.ok]
    assert np.diff(failed) == pytest.approx([0.01, 0.02, 0.04, 0.08])


def test_cadence_restarts_after_a_stall_instead_of_bursting():
    assert next_poll_time(due=1.0, period=0.01, now=1.005) == pytest.approx(1.01)
    assert next_poll_time(due=1.0, period=0.01, now=1.5) == pytest.approx(1.51)


def test_stuck_bus_never_raises_from_recv_and_recovers_when_released(clock):
    fake = make_fake(clock)
    source = open_fake(fake, clock)
    fake.stick_bus()
    assert samples(source, 5, timeout=0.05) == []     # each transfer blocks for the adapter timeout, then fails
    assert source.stats["errors"] >= 3
    assert "Errno 110" in source.last_error
    fake.release_bus()
    assert source.recv(timeout=3.0) is not None
    assert len(samples(source, 10)) == 10


def test_random_bus_errors_never_escape_recv(clock):
    fake = make_fake(clock, seed=3)
    source = open_fake(fake, clock)
    fake.error_rate = 0.2
    got = samples(source, 300)
    assert len(got) > 50
    assert source.stats["errors"] > 10
    assert source.stats["frames"] == len(got)


def test_chip_that_reset_itself_is_set_up_again(clock):
    fake = make_fake(clock, calibration_seconds=(0.0, 0.0, 0.0))
    source = open_fake(fake, clock)
    samples(source, 5)
    fake.power_on_reset()                               # brown-out: CONFIG mode, silent for 650 ms
    assert source.recv(timeout=3.0) is not None
    assert fake.mode == Mode.NDOF
    assert source.stats["reinits"] >= 1
    assert len(samples(source, 10)) == 10


def test_garbled_reads_are_counted_as_corrupt_and_dropped(clock):
    fake = make_fake(clock)
    source = open_fake(fake, clock)
    fake.garble_next(1)                                 # the data block comes back as 0xFF bytes
    assert source.recv(timeout=0.0) is None
    assert source.stats["corrupt"] == 1
    assert source.recv(timeout=0.1) is not None


def test_block_reads_never_exceed_32_bytes(clock):
    fake = make_fake(clock)
    source = open_fake(fake, clock)
    fake.error_rate = 0.05                              # recovery and re-initialisation read too
    samples(source, 200)
    assert 0 < fake.max_block_read <= bno055.SMBUS_BLOCK_MAX
    with pytest.raises(ValueError):
        fake.read_i2c_block_data(ADDRESS, 0x00, 33)   # as smbus2 refuses
    with pytest.raises(ValueError):
        bno055.BNO055(fake).read_block(0x00, 33)
