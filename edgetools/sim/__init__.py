"""Device simulation: fakes that stand in for hardware the board talks to, so tests and the
hardware-in-the-loop simulator run without it.

- `bno055_fake.FakeBNO055`: a BNO055 behind smbus2's methods, fed motion from a callable or arrays.
"""
