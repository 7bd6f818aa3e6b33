"""`edge listen`: the host-side reader of the board's pose stream, as a command and as a library.

    from edgetools.listen import Listener
    with Listener("/dev/ttyUSB0") as ear:            # or Listener(fd=...) on an open descriptor
        for frame in ear.poll(timeout=0.1):          # messages.PoseFrame objects
            ...

`record` (a binary file) keeps every byte read, as it came: a stream to attach to a bug report, or to
compare byte for byte (tests/test_golden.py).

It reports the frame rate, the latency (frame time to arrival, meaningful when the board and the
listener share a clock, as in the simulator; otherwise it includes the clock offset), and lost,
dropped and corrupt frames.
"""
import os
import select
import sys
import time
from collections import deque

import numpy as np

from firmware_bridge.wire import messages


class Listener:
    def __init__(self, port=None, baud=460800, fd=None, record=None):
        if (port is None) == (fd is None):
            raise ValueError("give a serial port path or an open file descriptor")
        self._serial = None
        if port is not None:
            import serial
            try:
                self._serial = serial.Serial(port, baud, timeout=0)
            except (serial.SerialException, OSError) as e:
                raise OSError(f"cannot open {port}: {e}") from None
            fd = self._serial.fileno()
        self.fd, self.record = fd, record
        self.reader = messages.FrameReader(accept=(messages.POSE_FRAME,))
        self.stats = self.reader.stats
        self.arrivals = deque(maxlen=240)
        self.latency_ms = deque(maxlen=240)

    def poll(self, timeout=0.0):
        """Pose frames that arrived, waiting up to `timeout` seconds for the first bytes. Raises OSError
        when the port is gone (unplugged): silence and a lost port are not the same."""
        try:
            ready, _, _ = select.select([self.fd], [], [], timeout)
            if not ready:
                return []
            chunk = os.read(self.fd, 65536)
        except (OSError, ValueError) as e:          # EIO after an unplug; a closed descriptor
            raise OSError(f"the pose stream's port is gone ({e}); is the board's link unplugged?") from None
        now = time.monotonic()
        if self.record is not None:
            self.record.write(chunk)
        frames = self.reader.feed(chunk)
        for f in frames:
            f.received = now
            self.arrivals.append(now)
            self.latency_ms.append((now - f.t) * 1000)
        return frames

    def rate(self):
        a = self.arrivals
        return (len(a) - 1) / (a[-1] - a[0]) if len(a) > 1 and a[-1] > a[0] else 0.0

    def status_line(self):
        lat = np.array(self.latency_ms) if self.latency_ms else np.zeros(1)
        s = self.stats
        return (f"edge listen | {self.rate():5.1f} Hz | latency p50 {np.median(lat):.1f} ms p99 {np.percentile(lat, 99):.1f} ms "
                f"| frames {s['frames']} | dropped {s.get('missed', 0)} | corrupt {s['corrupt']}")

    def close(self):
        if self._serial is not None:
            self._serial.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def status_loop(listener, seconds=None, every=0.25):
    """Read until `seconds` pass (or Ctrl-C), redrawing the status line in place on a terminal; the
    final line is always printed."""
    tty = sys.stderr.isatty()
    start = last = time.monotonic()
    code = 0
    try:
        while seconds is None or time.monotonic() - start < seconds:
            try:
                listener.poll(0.05)
            except OSError as e:
                sys.stderr.write(("\n" if tty else "") + f"edge listen: {e}\n")
                code = 1
                break
            if tty and time.monotonic() - last > every:
                last = time.monotonic()
                sys.stderr.write("\r" + listener.status_line() + "\x1b[K")
                sys.stderr.flush()
    except KeyboardInterrupt:
        pass
    sys.stderr.write(("\n" if tty else "") + listener.status_line() + "\n")
    return code


def main(args, loop=None):
    """`edge listen PORT [--baud B] [--seconds S] [--record FILE]`: open the port (and the recording), then
    run `loop(listener, seconds)`: the status line, or (edgecli, for --plot) viz.live's window."""
    loop = loop or status_loop
    record = None
    try:
        record = open(args.record, "wb") if getattr(args, "record", None) else None
        ear = Listener(args.port, args.baud, record=record)
    except OSError as e:            # library code raises; the command turns it into a line and an exit code
        print(f"edge listen: {e}", file=sys.stderr)
        if record is not None:
            record.close()
        return 2
    with ear:
        try:
            return loop(ear, args.seconds)
        finally:
            if record is not None:
                record.close()
