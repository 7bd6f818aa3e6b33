"""A non-blocking UDP sender shared by the OSC outputs (VMC, VRChat)."""
import socket

from firmware_bridge.outputs import PoseSink


class UdpSender(PoseSink):
    """Sends datagrams to one address. A full send buffer or an absent receiver drops the frame and
    counts it in `stats`; it never raises into, or stalls, the tracking loop."""

    def __init__(self, host, port):
        self.address = (host, port)
        self._socket = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._socket.setblocking(False)
        self.stats = {"frames": 0, "send_errors": 0}

    def send_datagrams(self, datagrams):
        for datagram in datagrams:
            try:
                self._socket.sendto(datagram, self.address)
            except OSError:
                self.stats["send_errors"] += 1
        self.stats["frames"] += 1

    def close(self):
        self._socket.close()
