"""A register-level fake BNO055 behind smbus2.SMBus's methods.

There is no /dev/i2c on the development machines, so tests and the simulator hand this object to the
driver where the board would use `smbus2.SMBus(1)`. It follows the datasheet (BST-BNO055-DS000-14,
rev 1.4) wherever the driver can observe it:

- the page 0 register map with its reset values; PAGE_ID selects page 1, which is stored but not
  interpreted (so a driver that forgets to select page 0 reads CHIP_ID 0x00);
- OPR_MODE switches take 7 ms from CONFIG and 19 ms to CONFIG (Table 3-6). The datasheet gives the
  times but not what the bus does meanwhile. By default the fake NACKs every access until the switch
  is done (the pessimistic reading: a driver that does not wait fails in tests); with
  `during_switch="stale"` it answers with the registers as they were (data from before the switch);
- output data is zero in CONFIG mode (section 3.3.1); the fusion outputs (quaternion, linear
  acceleration) are written only in fusion modes, once per 10 ms fusion cycle, from `motion(t)`;
  other data registers (raw sensors, Euler angles, gravity) stay zero;
- CALIB_STAT rises while a fusion mode runs (the magnetometer only in modes that use it); SYS_STATUS
  follows the mode: 0 idle in CONFIG, 5 fusion running, 6 running without fusion;
- writes to configuration registers outside CONFIG mode, and to read-only registers, are ignored
  (section 3.3.1) and listed in `ignored_writes`;
- SYS_TRIGGER's RST_SYS bit, and `power_on_reset()` (a brown-out), restore the reset values, lose the
  calibration and leave the chip silent (NACK) for the 650 ms power-on reset.

Faults: `fail_next`, `fail_between` and `error_rate` make transfers fail with OSError (errno EREMOTEIO
by default, what smbus2 raises when the chip does not acknowledge; pass errno.EIO for adapters that
report EIO); `stick_bus` makes every transfer block for the adapter timeout and fail with ETIMEDOUT
until `release_bus`; `garble_next` makes block reads return 0xFF bytes (a slave that let go of SDA).

Every transfer is recorded in `log` (BusAccess: time, operation, register, value or length, ok).
Time comes from `clock`; pass a `ManualClock` (and its `sleep` to the driver) to run without waiting.
"""
import errno
import os
import random
import time
from collections import deque
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from firmware_bridge.transports import bno055
from firmware_bridge.transports.bno055 import Mode, Reg

FUSION_RATE_HZ = 100.0             # fusion output data rate in the fusion modes (section 3.3)
PAGE_SIZE = 0x80
STUCK_BUS_TIMEOUT_S = 1.0          # Linux I2C adapters give up on a transfer after about a second

REG_INT_STA = 0x37
DATA_REGISTERS = range(0x08, 0x34)  # ACC_DATA .. GRV_DATA: all output data
SYS_TRIGGER_SELF_TEST = 0x01
SYS_TRIGGER_RST_INT = 0x40
SYS_TRIGGER_CLK_SEL = 0x80

# Page 0 reset values (register map, section 4.2); everything else resets to 0x00. After the power-on
# reset the chip is in CONFIG mode (section 3.2).
PAGE0_RESET = {
    Reg.CHIP_ID: bno055.CHIP_ID, 0x01: 0xFB, 0x02: 0x32, 0x03: 0x0F,   # chip, ACC, MAG, GYR IDs
    0x04: 0x08, 0x05: 0x03, 0x06: 0x15,                                # SW revision 0x0308, bootloader
    Reg.ST_RESULT: 0x0F,                                               # all four self tests passed
    Reg.UNIT_SEL: 0x80, Reg.OPR_MODE: Mode.CONFIG, 0x41: 0x24,         # AXIS_MAP_CONFIG 0x24
}
# Registers a host may change in CONFIG mode only (section 3.3.1): units, power mode, temperature
# source, axis remap, calibration offsets and radii.
CONFIG_REGISTERS = frozenset({Reg.UNIT_SEL, Reg.PWR_MODE, 0x40, 0x41, 0x42, *range(0x55, 0x6B)})


class BusAccess(NamedTuple):
    t: float              # fake clock at the start of the transfer
    operation: str        # "read", "write", "block_read", "block_write"
    register: int
    detail: int           # value written, or block length
    ok: bool              # False when the transfer raised


class ManualClock:
    """A clock that only moves when told to: pass `clock` as the clock and `clock.sleep` as sleep."""

    def __init__(self, start=0.0):
        self.now = float(start)

    def __call__(self):
        return self.now

    def sleep(self, seconds):
        self.now += max(0.0, float(seconds))


IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])


def still(t):
    """Default motion: level and at rest."""
    return IDENTITY, np.zeros(3)


def motion_from_arrays(quats, accels=None, rate=100.0, loop=True):
    """Replay recorded frames: motion(t) returns frame floor(t * rate), held until the next one.
    quats [N,4] (w, x, y, z); accels [N,3] linear acceleration in m/s^2, zeros when None."""
    quats = np.asarray(quats, np.float64)
    accels = np.zeros((len(quats), 3)) if accels is None else np.asarray(accels, np.float64)
    count = len(quats)

    def motion(t):
        index = int(np.floor(t * rate))
        index = index % count if loop else min(max(index, 0), count - 1)
        return quats[index], accels[index]

    return motion


def calibration_level(progress_s, full_after_s):
    """0..3: thirds of the time this sensor needs to be fully calibrated."""
    if full_after_s <= 0:
        return 3
    return min(3, int(3 * progress_s / full_after_s))


def os_error(code):
    """The OSError smbus2 lets through from the I2C ioctl."""
    return OSError(code, os.strerror(code))


@dataclass
class _Switch:
    target: Mode
    done_at: float


@dataclass(frozen=True)
class ChipBehaviour:
    """How the fake chip behaves: its CHIP_ID, the (gyroscope, accelerometer, magnetometer) seconds of
    fusion until each reads fully calibrated (0: calibrated from the start), its boot time, what it does
    to a read during a mode switch ("nack" or "stale"), the share of transfers that fail (seeded), how
    long a stuck bus holds, and how many transfers the log keeps."""
    chip_id: int = bno055.CHIP_ID
    calibration_seconds: tuple = (2.0, 6.0, 4.0)
    boot_seconds: float = 0.0
    during_switch: str = "nack"
    error_rate: float = 0.0
    seed: int = 0
    stuck_timeout: float = STUCK_BUS_TIMEOUT_S
    log_size: int = 10_000


class FakeBNO055:
    """A BNO055 on a fake I2C bus. `motion(t)` -> (quat [4], linear acceleration [3] or None), with t in
    seconds since the fake was created; `behaviour`: a ChipBehaviour (the datasheet's defaults)."""

    def __init__(self, motion=still, address=0x28, *, clock=time.monotonic, sleep=time.sleep, behaviour=None):
        b = self.behaviour = ChipBehaviour() if behaviour is None else behaviour
        if b.during_switch not in ("nack", "stale"):
            raise ValueError("during_switch is 'nack' or 'stale'")
        self.motion = motion
        self.address = address
        self.clock = clock
        self.sleep = sleep
        self.chip_id = b.chip_id
        self.calibration_seconds = dict(zip(("gyr", "acc", "mag"), b.calibration_seconds, strict=True))
        self.during_switch = b.during_switch
        self.error_rate = b.error_rate
        self.stuck_timeout = b.stuck_timeout
        self.log = deque(maxlen=b.log_size)
        self.ignored_writes = []
        self.max_block_read = 0
        self._random = random.Random(b.seed)
        self._fail_count = 0
        self._fail_errno = errno.EREMOTEIO
        self._fail_windows = []
        self._garble_count = 0
        self._stuck = False
        self._t0 = clock()
        self._power_on_reset(self._t0, b.boot_seconds)

    # ---- the SMBus surface ---------------------------------------------------------------------

    def read_byte_data(self, i2c_addr, register, force=None):
        self._transfer(i2c_addr, "read", register, 1)
        return self._register(register)

    def write_byte_data(self, i2c_addr, register, value, force=None):
        now = self._transfer(i2c_addr, "write", register, value)
        self._store(register, value & 0xFF, now)

    def read_i2c_block_data(self, i2c_addr, register, length, force=None):
        self.max_block_read = max(self.max_block_read, length)
        if length > bno055.SMBUS_BLOCK_MAX:
            raise ValueError(f"Desired block length over {bno055.SMBUS_BLOCK_MAX} bytes")   # as smbus2
        self._transfer(i2c_addr, "block_read", register, length)
        if self._garble_count:
            self._garble_count -= 1
            return [0xFF] * length
        # The register pointer auto-increments through a burst (section 4.6).
        return [self._register(register + i) for i in range(length)]

    def write_i2c_block_data(self, i2c_addr, register, data, force=None):
        if len(data) > bno055.SMBUS_BLOCK_MAX:
            raise ValueError(f"Data length cannot exceed {bno055.SMBUS_BLOCK_MAX} bytes")
        now = self._transfer(i2c_addr, "block_write", register, len(data))
        for i, value in enumerate(data):
            self._store(register + i, value & 0xFF, now)

    def close(self):
        pass

    # ---- fault injection -----------------------------------------------------------------------

    def fail_next(self, count, code=errno.EREMOTEIO):
        """The next `count` transfers fail with OSError(code)."""
        self._fail_count = count
        self._fail_errno = code

    def fail_between(self, start, end, code=errno.EREMOTEIO):
        """Transfers fail while start <= elapsed() < end (seconds since the fake was created)."""
        self._fail_windows.append((start, end, code))

    def stick_bus(self):
        """SDA held low: every transfer blocks for `stuck_timeout` and fails with ETIMEDOUT."""
        self._stuck = True

    def release_bus(self):
        self._stuck = False

    def garble_next(self, count):
        """The next `count` block reads return 0xFF bytes instead of register contents."""
        self._garble_count = count

    def power_on_reset(self, duration=bno055.RESET_S):
        """Reset as after a brown-out or a pulse on nRESET: defaults, CONFIG mode, calibration lost."""
        self._power_on_reset(self.clock(), duration)

    # ---- state a test may look at --------------------------------------------------------------

    def elapsed(self):
        return self.clock() - self._t0

    @property
    def mode(self):
        """The mode the chip is in (the old one while a switch is under way)."""
        return self._mode

    @property
    def calibration(self):
        self._advance(self.clock())
        return bno055.calibration_levels(self._page0[Reg.CALIB_STAT])

    # ---- the chip ------------------------------------------------------------------------------

    def _transfer(self, address, operation, register, detail):
        """What every transfer goes through before the chip's registers are touched; returns the time."""
        now = self.clock()
        ok = False
        try:
            if self._stuck:
                self.sleep(self.stuck_timeout)
                raise os_error(errno.ETIMEDOUT)
            code = self._injected_fault(now)
            if code:
                raise os_error(code)
            if address != self.address:
                raise os_error(errno.EREMOTEIO)          # nobody acknowledges the address
            self._advance(now)
            if self._booting_until is not None:
                raise os_error(errno.EREMOTEIO)          # power-on reset under way
            if self._switch is not None and self.during_switch == "nack":
                raise os_error(errno.EREMOTEIO)          # mode switch under way
            ok = True
            return now
        finally:
            self.log.append(BusAccess(now, operation, register, detail, ok))

    def _injected_fault(self, now):
        if self._fail_count > 0:
            self._fail_count -= 1
            return self._fail_errno
        elapsed = now - self._t0
        for start, end, code in self._fail_windows:
            if start <= elapsed < end:
                return code
        if self.error_rate and self._random.random() < self.error_rate:
            return errno.EREMOTEIO
        return 0

    def _power_on_reset(self, now, duration):
        self._page0 = bytearray(PAGE_SIZE)
        for register, value in PAGE0_RESET.items():
            self._page0[register] = value
        self._page0[Reg.CHIP_ID] = self.chip_id
        self._page1 = bytearray(PAGE_SIZE)
        self._page = 0
        self._mode = Mode.CONFIG
        self._switch = None
        self._fusion_since = None
        self._calibration_progress = {"gyr": 0.0, "acc": 0.0, "mag": 0.0}
        self._last_advance = now
        self._booting_until = now + duration if duration > 0 else None

    def _advance(self, now):
        """Bring the registers up to `now`: finish a boot or a mode switch, run fusion and calibration."""
        if self._booting_until is not None:
            if now < self._booting_until:
                return
            self._last_advance = self._booting_until
            self._booting_until = None
        if self._switch is not None and now >= self._switch.done_at:
            self._finish_switch()
        if self._is_fusing():
            self._calibrate(now - self._last_advance)
            self._write_fusion_output(now)
        self._last_advance = now
        self._page0[Reg.SYS_STATUS] = self._sys_status()

    def _finish_switch(self):
        switch, self._switch = self._switch, None
        self._mode = switch.target
        self._last_advance = switch.done_at
        if switch.target in bno055.FUSION_MODES:
            self._fusion_since = switch.done_at
        else:
            # CONFIG resets all output data to zero (3.3.1); non-fusion modes write no fusion output.
            self._fusion_since = None
            for register in DATA_REGISTERS:
                self._page0[register] = 0

    def _is_fusing(self):
        return self._switch is None and self._fusion_since is not None

    def _sys_status(self):
        if self._switch is not None:
            return self._page0[Reg.SYS_STATUS]
        if self._mode == Mode.CONFIG:
            return bno055.SYS_STATUS_IDLE
        if self._mode in bno055.FUSION_MODES:
            return bno055.SYS_STATUS_FUSION_RUNNING
        return bno055.SYS_STATUS_RUNNING_NO_FUSION

    def _calibrate(self, dt):
        sensors = ["gyr", "acc"] + (["mag"] if self._mode in bno055.MAGNETOMETER_FUSION_MODES else [])
        for sensor in sensors:
            self._calibration_progress[sensor] += dt
        levels = {s: calibration_level(self._calibration_progress[s], self.calibration_seconds[s])
                  for s in ("gyr", "acc", "mag")}
        # The system level follows the sensors the fusion mode relies on.
        system = min(levels[s] for s in sensors)
        self._page0[Reg.CALIB_STAT] = bno055.pack_calib_stat(system, levels["gyr"], levels["acc"], levels["mag"])

    def _write_fusion_output(self, now):
        # Outputs change once per fusion cycle, so polling faster than 100 Hz reads the same values again.
        cycles = np.floor((now - self._fusion_since) * FUSION_RATE_HZ)
        output_time = self._fusion_since + cycles / FUSION_RATE_HZ
        quat, accel = self.motion(output_time - self._t0)
        quat = np.asarray(quat, np.float64)
        quat = quat / np.linalg.norm(quat)
        accel = np.zeros(3) if accel is None else accel
        accel_in_mg = bool(self._page0[Reg.UNIT_SEL] & bno055.UNIT_SEL_ACCEL_MG)
        self._page0[Reg.QUA_DATA:Reg.QUA_DATA + 8] = bno055.encode_quaternion(quat)
        self._page0[Reg.LIA_DATA:Reg.LIA_DATA + 6] = bno055.encode_acceleration(accel, accel_in_mg)

    def _register(self, register):
        if register == Reg.PAGE_ID:
            return self._page
        if register >= PAGE_SIZE:
            return 0
        return (self._page1 if self._page == 1 else self._page0)[register]

    def _store(self, register, value, now):
        if register == Reg.PAGE_ID:
            if value in (0, 1):
                self._page = value
            else:
                self.ignored_writes.append((register, value))
        elif register >= PAGE_SIZE:
            self.ignored_writes.append((register, value))
        elif self._page == 1:
            if self._in_config():
                self._page1[register] = value
            else:
                self.ignored_writes.append((register, value))
        elif register == Reg.OPR_MODE:
            self._start_switch(value, now)
        elif register == Reg.SYS_TRIGGER:
            self._trigger(value, now)
        elif register in CONFIG_REGISTERS and self._in_config():
            self._page0[register] = value
        else:
            self.ignored_writes.append((register, value))

    def _in_config(self):
        return self._mode == Mode.CONFIG and self._switch is None

    def _start_switch(self, value, now):
        target = value & 0x0F
        if target > Mode.NDOF:
            self.ignored_writes.append((Reg.OPR_MODE, value))
            return
        self._page0[Reg.OPR_MODE] = target
        if target == self._mode and self._switch is None:
            return
        self._switch = _Switch(Mode(target), now + bno055.switch_time(target))

    def _trigger(self, value, now):
        if value & bno055.SYS_TRIGGER_RST_SYS:
            self._power_on_reset(now, bno055.RESET_S)
            return
        if value & SYS_TRIGGER_RST_INT:
            self._page0[REG_INT_STA] = 0
        if value & SYS_TRIGGER_SELF_TEST and self._in_config():
            self._page0[Reg.ST_RESULT] = 0x0F
        self._page0[Reg.SYS_TRIGGER] = value & SYS_TRIGGER_CLK_SEL
