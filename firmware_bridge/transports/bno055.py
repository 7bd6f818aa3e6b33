"""Bosch BNO055 driver over an SMBus-like object: the device the `i2c` transport reaches.

The BNO055 runs its own sensor fusion and keeps the result in registers; the board only has to put
the chip in NDOF mode and read those registers. `bus` is anything with smbus2.SMBus's methods
(`read_byte_data`, `write_byte_data`, `read_i2c_block_data`): a real `smbus2.SMBus(1)` on the board,
`edgetools.sim.bno055_fake.FakeBNO055` in tests and the simulator.

Datasheet references are to BST-BNO055-DS000-14, revision 1.4 (June 2016). Only register page 0 is used.

Bus errors surface as OSError (what smbus2 raises on a NACK or a bus timeout); this module does not
retry. Retrying, backoff and re-initialisation live in the transport (`firmware_bridge.transports.i2c`),
which decides what an error means for the sample stream.
"""
import time
from dataclasses import dataclass
from enum import IntEnum
from typing import NamedTuple

import numpy as np

from firmware_bridge.transports.base import TransportError
from firmware_bridge.wire import q14

# I2C addresses (Table 4-7): COM3 low -> 0x28 (most breakout boards), COM3 high -> 0x29.
ADDRESSES = (0x28, 0x29)
CHIP_ID = 0xA0

# smbus2 refuses block reads longer than this (I2C_SMBUS_BLOCK_MAX); longer reads need i2c_rdwr.
SMBUS_BLOCK_MAX = 32
OUTPUT_BLOCK_LENGTH = 14           # QUA_DATA (8 bytes) and LIA_DATA (6 bytes) are adjacent
STATUS_BLOCK_LENGTH = 6            # CALIB_STAT, ST_RESULT, INT_STA, SYS_CLK_STATUS, SYS_STATUS, SYS_ERR


class Reg(IntEnum):
    """Page 0 registers this driver touches (register map, section 4.2)."""
    CHIP_ID = 0x00
    PAGE_ID = 0x07
    QUA_DATA = 0x20        # quaternion W, X, Y, Z: int16 little-endian, 8 bytes
    LIA_DATA = 0x28        # linear acceleration X, Y, Z: int16 little-endian, 6 bytes
    CALIB_STAT = 0x35
    ST_RESULT = 0x36
    SYS_STATUS = 0x39
    SYS_ERR = 0x3A
    UNIT_SEL = 0x3B
    OPR_MODE = 0x3D
    PWR_MODE = 0x3E
    SYS_TRIGGER = 0x3F


class Mode(IntEnum):
    """OPR_MODE values (Table 3-5)."""
    CONFIG = 0x00
    ACCONLY = 0x01
    MAGONLY = 0x02
    GYROONLY = 0x03
    ACCMAG = 0x04
    ACCGYRO = 0x05
    MAGGYRO = 0x06
    AMG = 0x07
    IMU = 0x08
    COMPASS = 0x09
    M4G = 0x0A
    NDOF_FMC_OFF = 0x0B
    NDOF = 0x0C


FUSION_MODES = frozenset({Mode.IMU, Mode.COMPASS, Mode.M4G, Mode.NDOF_FMC_OFF, Mode.NDOF})
MAGNETOMETER_FUSION_MODES = frozenset({Mode.COMPASS, Mode.M4G, Mode.NDOF_FMC_OFF, Mode.NDOF})

# Operating mode switching time (Table 3-6).
SWITCH_FROM_CONFIG_S = 0.007
SWITCH_TO_CONFIG_S = 0.019
# Power-on reset: register map back to defaults, CONFIG mode, chip silent meanwhile (Table 0-2).
RESET_S = 0.650
# How long `initialise` keeps asking for the chip ID: a chip powered up with the board may still be booting.
BOOT_WAIT_S = 0.850
BOOT_POLL_S = 0.010

PWR_MODE_NORMAL = 0x00
UNIT_SEL_ACCEL_MG = 0x01           # UNIT_SEL bit 0: 0 = m/s^2, 1 = mg (Table 3-11)
SYS_TRIGGER_RST_SYS = 0x20         # SYS_TRIGGER bit 5: power-on reset

# SYS_STATUS values (section 4.3.58).
SYS_STATUS_IDLE = 0
SYS_STATUS_ERROR = 1
SYS_STATUS_FUSION_RUNNING = 5
SYS_STATUS_RUNNING_NO_FUSION = 6

SYS_ERR_TEXT = {
    0: "no error", 1: "peripheral initialization error", 2: "system initialization error",
    3: "self test failed", 4: "register map value out of range", 5: "register map address out of range",
    6: "register map write error", 7: "low power mode not available for selected operation mode",
    8: "accelerometer power mode not available", 9: "fusion algorithm configuration error",
    10: "sensor configuration error",
}

# Output scaling: 1 quaternion unit = 2^14 LSB (Table 3-31); 1 m/s^2 = 100 LSB (Table 3-33).
QUAT_LSB = 16384
ACCEL_LSB_PER_MS2 = 100
STANDARD_GRAVITY = 9.80665         # for the mg unit: 1 mg = 1 LSB

# A fused quaternion is unit length to within Q14 rounding; a read far from it is a damaged transfer.
QUAT_NORM_TOLERANCE = q14.NORM_TOLERANCE


class CalibrationLevels(NamedTuple):
    """CALIB_STAT split into its four 2-bit fields, each 0 (uncalibrated) to 3 (fully calibrated)."""
    sys: int
    gyr: int
    acc: int
    mag: int


@dataclass
class Reading:
    """One poll of the fused output registers."""
    t: float                 # host clock right after the data block read (the chip has no timestamp)
    quat: np.ndarray         # [4] (w, x, y, z) as read, not renormalised
    accel: np.ndarray        # [3] linear acceleration, m/s^2, sensor frame
    calib_stat: int          # CALIB_STAT byte
    sys_status: int          # SYS_STATUS byte
    sys_err: int             # SYS_ERR byte


# ---- pure conversions -------------------------------------------------------------------------

def decode_quaternion(block):
    """8 register bytes (W, X, Y, Z int16 LE, Q14) -> [4] float quaternion as read."""
    return q14.from_bytes(block)


def encode_quaternion(quat):
    """[4] quaternion -> 8 register bytes (what the chip would hold: its fused output is unit)."""
    return q14.to_bytes(quat)


def decode_acceleration(block, accel_in_mg=False):
    """6 register bytes (X, Y, Z int16 LE) -> [3] m/s^2."""
    counts = np.frombuffer(bytes(block), dtype="<i2").astype(np.float64)
    return counts * (STANDARD_GRAVITY / 1000.0) if accel_in_mg else counts / ACCEL_LSB_PER_MS2


def encode_acceleration(accel, accel_in_mg=False):
    """[3] m/s^2 -> 6 register bytes in the unit UNIT_SEL selects."""
    accel = np.asarray(accel, np.float64)
    scaled = accel * (1000.0 / STANDARD_GRAVITY) if accel_in_mg else accel * ACCEL_LSB_PER_MS2
    return np.clip(np.round(scaled), -32768, 32767).astype("<i2").tobytes()


def calibration_levels(calib_stat):
    """CALIB_STAT byte -> CalibrationLevels (bits 7-6 SYS, 5-4 GYR, 3-2 ACC, 1-0 MAG; section 4.3.54)."""
    return CalibrationLevels((calib_stat >> 6) & 3, (calib_stat >> 4) & 3, (calib_stat >> 2) & 3, calib_stat & 3)


def pack_calib_stat(sys, gyr, acc, mag):
    return (sys & 3) << 6 | (gyr & 3) << 4 | (acc & 3) << 2 | (mag & 3)


def pack_status(calib_stat, sys_status, sys_err):
    """The TrackerSample.status of an I2C sample: CALIB_STAT in bits 0-7, SYS_STATUS 8-15, SYS_ERR 16-23.
    The low byte has the same layout as the CAN tracker frames' status byte."""
    return (calib_stat & 0xFF) | (sys_status & 0xFF) << 8 | (sys_err & 0xFF) << 16


def unpack_status(status):
    """TrackerSample.status of an I2C sample -> (CalibrationLevels, SYS_STATUS, SYS_ERR)."""
    return calibration_levels(status & 0xFF), (status >> 8) & 0xFF, (status >> 16) & 0xFF


def switch_time(new_mode):
    """Seconds to wait after writing OPR_MODE before touching the chip again (Table 3-6)."""
    return SWITCH_TO_CONFIG_S if new_mode == Mode.CONFIG else SWITCH_FROM_CONFIG_S


def is_plausible_quaternion(quat, tolerance=QUAT_NORM_TOLERANCE):
    """True for a fused output: finite and unit length within `tolerance`. All zeros means no fusion output."""
    return bool(q14.is_unit(quat, tolerance))


def unit_sel_for_metres_per_second_squared(unit_sel):
    """Clear the mg bit, keep the other unit choices as they were."""
    return unit_sel & ~UNIT_SEL_ACCEL_MG & 0xFF


# ---- the driver ---------------------------------------------------------------------------------

class BNO055Error(TransportError):
    """The chip answers but is not a working BNO055 (wrong chip ID, system error after set-up)."""


class BNO055:
    """Register-level access to one BNO055. `clock` and `sleep` are injectable so tests run instantly."""

    def __init__(self, bus, address=0x28, *, clock=time.monotonic, sleep=time.sleep):
        self.bus = bus
        self.address = address
        self.clock = clock
        self.sleep = sleep
        self.mode = None                   # last mode written, None until `initialise` ran

    # -- set-up ----------------------------------------------------------------------------------

    def initialise(self, boot_wait=BOOT_WAIT_S, mode=Mode.NDOF):
        """Bring the chip from any state into `mode` (section 3.3): page 0, chip ID check, CONFIG,
        normal power, m/s^2, then the fusion mode. Raises OSError when the bus fails and BNO055Error
        when the chip answers wrongly. `boot_wait` > 0 keeps asking for the chip ID that long, for a
        chip that is still in its power-on reset."""
        self.wait_for_chip(boot_wait)
        self.set_mode(Mode.CONFIG)
        # PWR_MODE and UNIT_SEL are writable only in CONFIG mode (section 3.3.1).
        self.write(Reg.PWR_MODE, PWR_MODE_NORMAL)
        self.write(Reg.UNIT_SEL, unit_sel_for_metres_per_second_squared(self.read(Reg.UNIT_SEL)))
        self.set_mode(mode)
        status, error = self.read_block(Reg.SYS_STATUS, 2)
        if status == SYS_STATUS_ERROR:
            raise BNO055Error(f"BNO055 at {self.address:#04x} reports a system error after set-up: "
                              f"SYS_ERR={error} ({SYS_ERR_TEXT.get(error, 'unknown')})")

    def wait_for_chip(self, boot_wait=BOOT_WAIT_S):
        """Select register page 0 and check CHIP_ID, retrying for `boot_wait` seconds."""
        deadline = self.clock() + boot_wait
        while True:
            try:
                # Page 1 holds other registers at the same addresses; a previous user may have left it selected.
                self.write(Reg.PAGE_ID, 0)
                chip_id = self.read(Reg.CHIP_ID)
                if chip_id == CHIP_ID:
                    return
                if self.clock() >= deadline:
                    raise BNO055Error(
                        f"the chip at {self.address:#04x} reports CHIP_ID {chip_id:#04x}, a BNO055 reports "
                        f"{CHIP_ID:#04x}: another device answers at this address, or the BNO055 is not "
                        f"booting (check its power and the PS0/PS1 pins select I2C)")
            except OSError:
                if self.clock() >= deadline:
                    raise
            self.sleep(BOOT_POLL_S)

    def set_mode(self, mode):
        """Write OPR_MODE and wait the datasheet switching time before the next access."""
        self.write(Reg.OPR_MODE, int(mode))
        self.sleep(switch_time(mode))
        self.mode = Mode(mode)

    def reset(self):
        """Power-on reset via SYS_TRIGGER (section 3.2): loses calibration, needs `initialise` afterwards."""
        self.write(Reg.SYS_TRIGGER, SYS_TRIGGER_RST_SYS)
        self.sleep(RESET_S)
        self.mode = None

    # -- reading ---------------------------------------------------------------------------------

    def read_output(self):
        """One Reading in two burst reads: quaternion and linear acceleration (0x20-0x2D, 14 bytes),
        then CALIB_STAT to SYS_ERR (0x35-0x3A, 6 bytes). One burst keeps W, X, Y, Z and the acceleration
        from the same fusion output (byte-by-byte reads could straddle an update), and fewer transfers
        mean fewer chances for a bus error per sample."""
        data = self.read_block(Reg.QUA_DATA, OUTPUT_BLOCK_LENGTH)
        t = self.clock()
        status = self.read_block(Reg.CALIB_STAT, STATUS_BLOCK_LENGTH)
        return Reading(t=t, quat=decode_quaternion(data[:8]), accel=decode_acceleration(data[8:]),
                       calib_stat=status[0], sys_status=status[Reg.SYS_STATUS - Reg.CALIB_STAT],
                       sys_err=status[Reg.SYS_ERR - Reg.CALIB_STAT])

    def read_mode(self):
        return self.read(Reg.OPR_MODE) & 0x0F

    # -- bus primitives --------------------------------------------------------------------------

    def read(self, register):
        return self.bus.read_byte_data(self.address, int(register))

    def write(self, register, value):
        self.bus.write_byte_data(self.address, int(register), int(value))

    def read_block(self, register, length):
        if length > SMBUS_BLOCK_MAX:
            raise ValueError(f"SMBus block reads stop at {SMBUS_BLOCK_MAX} bytes, asked for {length}")
        return bytes(self.bus.read_i2c_block_data(self.address, int(register), length))
