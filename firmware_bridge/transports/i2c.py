"""The `i2c` scheme: one BNO055 on a Linux I2C bus, polled at a fixed rate.

    source = open_source("i2c://1/0x28?tracker=waist&rate=100")    # /dev/i2c-1, address 0x28
    sample = source.recv(timeout=0.02)                               # TrackerSample or None

URL: `i2c://BUS/ADDRESS?tracker=NAME&rate=HZ`. BUS is the number in /dev/i2c-BUS; ADDRESS is 0x28
(COM3 low, most breakout boards) or 0x29 (COM3 high), 0x28 when left out; `tracker` names the
sample's tracker ("waist" by default); `rate` is the poll rate in Hz, at most the chip's 100 Hz
fusion rate (100 by default).

The BNO055 has no timestamp: a sample's `t` and `received` are the host's time.monotonic() right
after the quaternion is read. `status` packs CALIB_STAT, SYS_STATUS and SYS_ERR
(`firmware_bridge.transports.bno055.unpack_status` splits it); the quaternion and linear acceleration are in the
chip's own frames, which the calibration stage maps onto the body.

Opening checks the chip ID, switches CONFIG -> NDOF with the datasheet settle times and tries the
set-up three times before giving up with a TransportError. After that, bus errors never escape
`recv`: each one is counted in `stats["errors"]` (the latest in `last_error`), the next try waits
twice as long as the one before (10 ms up to 1 s), and after three failures in a row the chip is set
up again from scratch (counted in `stats["reinits"]`), which also recovers a chip that reset itself.
A damaged read (a quaternion that is not unit length) counts in `stats["corrupt"]`.

Raspberry Pi: enable I2C with `sudo raspi-config nonint do_i2c 0` (or raspi-config > Interface Options
> I2C) and reboot; `i2cdetect -y 1` should then show 28. The Pi's I2C controller mishandles the clock
stretching the BNO055 uses; if reads fail often, slow the bus down (`dtparam=i2c_arm_baudrate=10000`
in config.txt) or use the software `i2c-gpio` overlay.
"""
import time
from dataclasses import dataclass

import numpy as np

from firmware_bridge.transports.bno055 import (ADDRESSES, BNO055, BOOT_WAIT_S, SYS_STATUS_FUSION_RUNNING,
                                    is_plausible_quaternion, pack_status)
from firmware_bridge.samples import TrackerSample
from firmware_bridge.transports.base import Source, TransportError

DEFAULT_TRACKER = "waist"
DEFAULT_RATE_HZ = 100.0
MAX_RATE_HZ = 100.0                 # the fusion output rate; polling faster re-reads the same output
REINIT_AFTER_FAILURES = 3
FIRST_BACKOFF_S = 0.010
MAX_BACKOFF_S = 1.0


@dataclass(frozen=True)
class Recovery:
    """How a source rides out bus errors: back off from first_backoff (s) doubling to max_backoff, and set
    the chip up again after reinit_after failed polls in a row."""
    reinit_after: int = REINIT_AFTER_FAILURES
    first_backoff: float = FIRST_BACKOFF_S
    max_backoff: float = MAX_BACKOFF_S
SET_UP_ATTEMPTS = 3


def tracker_names(parsed):
    return [parsed[3].get("tracker", DEFAULT_TRACKER)]


def open(url, parsed, bus=None, *, clock=time.monotonic, sleep=time.sleep, recovery=None):
    """Open the BNO055 the URL names. `bus`: an SMBus-like object to use instead of /dev/i2c-BUS
    (tests pass a FakeBNO055; the simulator's sim:// scheme does the same); `clock`/`sleep` are
    injectable; `recovery` goes to BNO055Source (default Recovery())."""
    _, netloc, path, _ = parsed
    bus_number = parse_bus_number(netloc, url)
    parse_address(path, url)
    owns_bus = bus is None
    if owns_bus:
        bus = open_smbus(bus_number)
    return open_on_bus(url, parsed, bus, owns_bus, clock=clock, sleep=sleep, recovery=recovery)


def open_on_bus(url, parsed, bus, owns_bus=False, *, clock=time.monotonic, sleep=time.sleep, recovery=None):
    """The BNO055Source for the chip the URL's address and query name, on an open SMBus-like `bus`."""
    _, netloc, path, query = parsed
    bus_number = netloc or "?"
    address = parse_address(path, url)
    tracker = query.get("tracker", DEFAULT_TRACKER)
    rate = parse_rate(query.get("rate"), url)
    chip = BNO055(bus, address, clock=clock, sleep=sleep)
    try:
        set_up(chip, sleep)
    except OSError as error:
        _close_if_owned(bus, owns_bus)
        raise TransportError(
            f"no BNO055 answers at {address:#04x} on /dev/i2c-{bus_number} ({error}): check power and "
            f"wiring (SDA, SCL, GND), that COM3 selects this address (low 0x28, high 0x29), and what "
            f"`i2cdetect -y {bus_number}` lists") from error
    except TransportError:
        _close_if_owned(bus, owns_bus)
        raise
    return BNO055Source(chip, tracker, rate, url=url, clock=clock, sleep=sleep,
                        recovery=recovery, on_close=bus.close if owns_bus else None)


def set_up(chip, sleep, attempts=SET_UP_ATTEMPTS):
    """chip.initialise(), tried again after a bus error: one glitch should not fail the whole start-up."""
    for attempt in range(1, attempts + 1):
        try:
            chip.initialise(boot_wait=BOOT_WAIT_S if attempt == 1 else 0.0)
            return
        except OSError:
            if attempt == attempts:
                raise
            sleep(backoff_delay(attempt))


# ---- URL parts ------------------------------------------------------------------------------------

def parse_bus_number(netloc, url):
    if not netloc.isdigit():
        raise TransportError(f"{url!r}: give the I2C bus number after i2c://, e.g. i2c://1/0x28 for /dev/i2c-1")
    return int(netloc)


def parse_address(path, url):
    text = path.strip("/")
    if not text:
        return ADDRESSES[0]
    try:
        address = int(text, 0)
    except ValueError:
        address = None
    if address not in ADDRESSES:
        raise TransportError(f"{url!r}: a BNO055 answers at 0x28 (COM3 low) or 0x29 (COM3 high), not {text!r}")
    return address


def parse_rate(text, url):
    if text is None:
        return DEFAULT_RATE_HZ
    try:
        rate = float(text)
    except ValueError:
        rate = 0.0
    if not 0.0 < rate <= MAX_RATE_HZ:
        raise TransportError(f"{url!r}: rate is the poll rate in Hz, above 0 and at most {MAX_RATE_HZ:g} "
                             f"(the BNO055's fusion rate), not {text!r}")
    return rate


def open_smbus(bus_number):
    """smbus2.SMBus(bus_number), with errors that say what to do."""
    try:
        import smbus2
    except ImportError as error:
        raise TransportError("the i2c transport needs smbus2: pip install smbus2") from error
    device = f"/dev/i2c-{bus_number}"
    try:
        return smbus2.SMBus(bus_number)
    except FileNotFoundError as error:
        raise TransportError(
            f"{device} does not exist. Enable I2C: on a Raspberry Pi run `sudo raspi-config nonint do_i2c 0` "
            f"(or raspi-config > Interface Options > I2C; or add dtparam=i2c_arm=on to /boot/firmware/config.txt) "
            f"and reboot; elsewhere load the driver with `sudo modprobe i2c-dev`. `ls /dev/i2c-*` lists the "
            f"buses there are") from error
    except PermissionError as error:
        raise TransportError(f"no permission to open {device}: add your user to the i2c group "
                             f"(`sudo usermod -aG i2c $USER`) and log in again") from error


def _close_if_owned(bus, owns_bus):
    if owns_bus:
        bus.close()


# ---- timing ---------------------------------------------------------------------------------------

def backoff_delay(failures, first=FIRST_BACKOFF_S, cap=MAX_BACKOFF_S):
    """Wait before the next try after `failures` failures in a row: first, 2*first, 4*first ... cap."""
    return min(cap, first * 2.0 ** min(failures - 1, 30))


def next_poll_time(due, period, now):
    """Keep a steady cadence; after a stall, restart it from now instead of bursting to catch up."""
    due += period
    return due if due > now else now + period


# ---- the source -----------------------------------------------------------------------------------

class BNO055Source(Source):
    """Polls an initialised BNO055 at `rate` Hz and turns each read into a TrackerSample."""

    def __init__(self, chip, tracker=DEFAULT_TRACKER, rate=DEFAULT_RATE_HZ, *, url="", clock=time.monotonic,
                 sleep=time.sleep, recovery=None, on_close=None):
        super().__init__(clock)
        self.stats["reinits"] = 0
        self.last_error = None
        self.url = url
        self.chip = chip
        self.tracker = tracker
        self.period = 1.0 / rate
        recovery = Recovery() if recovery is None else recovery
        self.reinit_after = recovery.reinit_after
        self.first_backoff = recovery.first_backoff
        self.max_backoff = recovery.max_backoff
        self._clock = clock
        self._sleep = sleep
        self._on_close = on_close
        self._next_poll = clock()
        self._failures_in_a_row = 0
        self._chip_needs_setup = False

    def _recv_internal(self, timeout):
        """Wait for the next poll time (or to the end of `timeout` if it is later), then poll once."""
        if timeout is not None and self._next_poll > self._clock() + timeout:
            self._sleep_until(self._clock() + timeout)
            return None
        self._sleep_until(self._next_poll)
        return self._poll()

    @property
    def state(self):
        if self._closed:
            return "closed"
        return "error" if self._failures_in_a_row else "active"

    def _close_internal(self):
        if self._on_close is not None:
            self._on_close()
            self._on_close = None

    def _poll(self):
        """One read; a sample, or None after counting what went wrong and scheduling the next try."""
        try:
            if self._chip_needs_setup:
                self.stats["reinits"] += 1
                self.chip.initialise(boot_wait=0.0)   # a chip still booting fails here and is retried later
                self._chip_needs_setup = False
            reading = self.chip.read_output()
        except (OSError, TransportError) as error:
            self._count_failure(f"{type(error).__name__}: {error}")
            return None
        if reading.sys_status != SYS_STATUS_FUSION_RUNNING:
            # The chip reset itself (brown-out, watchdog) or reports a system error: set it up again.
            self._count_failure(f"BNO055 not fusing: SYS_STATUS={reading.sys_status} SYS_ERR={reading.sys_err}")
            self._chip_needs_setup = True
            return None
        self._failures_in_a_row = 0
        self._next_poll = next_poll_time(self._next_poll, self.period, reading.t)
        if not is_plausible_quaternion(reading.quat):
            self.stats["corrupt"] += 1
            return None
        self.stats["frames"] += 1
        quat = reading.quat / np.linalg.norm(reading.quat)
        return TrackerSample(tracker=self.tracker, t=reading.t, quat=quat, accel=reading.accel,
                             status=pack_status(reading.calib_stat, reading.sys_status, reading.sys_err),
                             received=reading.t)

    def _count_failure(self, description):
        self.stats["errors"] += 1
        self.last_error = description
        self._failures_in_a_row += 1
        if self._failures_in_a_row >= self.reinit_after:
            self._chip_needs_setup = True
        self._next_poll = self._clock() + backoff_delay(self._failures_in_a_row, self.first_backoff, self.max_backoff)

    def _sleep_until(self, moment):
        delay = moment - self._clock()
        if delay > 0:
            self._sleep(delay)
