"""Transports: one small interface, one module per URL scheme (pyserial's URL handlers and python-can's
BusABC are the models).

    source = open_source("serial:///dev/ttyUSB0?baud=921600")   # tracker hub or headset link
    source = open_source("i2c://1/0x28")                        # a BNO055 on I2C bus 1 (bno055.py drives it)
    source = open_source("can://virtual/bus0")                  # CAN tracker nodes (python-can)
    source = open_source("slimevr://0.0.0.0:6969?trackers=...") # SlimeVR trackers over UDP
    source = open_source("webxr://0.0.0.0:8443")                # the headset's browser (HTTPS + WebSocket)
    sample = source.recv(timeout=0.01)                          # TrackerSample / HeadsetSample / None
    source.close()
"""
from firmware_bridge.transports.base import (DeviceUnavailable, Source, TransportError, open_source,  # noqa: F401
                                             parse_url, register_scheme, tracker_names)
