"""The transport interface (python-can's BusABC is the model) and the URL opener (pyserial's URL handlers).

    source = open_source("serial:///dev/ttyUSB0?role=hub&trackers=0:waist,1:l_foot")
    sample = source.recv(timeout=0.01)          # TrackerSample / HeadsetSample / None

`Source.recv(timeout)` is one template that owns the deadline; a transport implements only
`_recv_internal(timeout)`: wait at most `timeout` seconds for input, then take what is already there
without waiting, and return one sample or None. Input that is already queued is always read, so a
`recv(timeout=0)` loop drains a source; each transport bounds how much one call reads, so a flood
cannot hold the caller.

A URL scheme is a plug-in: a module with `open(url, parsed, **kw) -> Source` (and, to let a config
check names before start-up, `tracker_names(parsed) -> [name]`), each parsing its own query. The
built-in schemes are registered below; `register_scheme` adds one, and so does an installed package
through the `edgepose.transports` entry-point group (as python-can's `can.interface`).
"""
import importlib
import time
from abc import ABC, abstractmethod
from importlib.metadata import entry_points
from urllib.parse import parse_qs, urlparse

ACTIVE, ERROR, CLOSED = "active", "error", "closed"


class TransportError(RuntimeError):
    """A source that cannot be opened or has failed for good; the message says what to check."""


class DeviceUnavailable(TransportError):
    """The device a well-formed URL names cannot be opened now: not plugged in yet, unplugged, not
    enumerated, or busy. A service waits for it and retries; a mistake in the URL itself (a bad baud
    rate, an unknown role) is a plain TransportError, reported at start-up."""


class Source(ABC):
    """A device link that yields timestamped samples. Implementations never raise on one bad frame:
    they count it in `stats` and carry on. `state` is ACTIVE, ERROR (the device reports a fault, e.g.
    a CAN bus-off, and may recover) or CLOSED."""

    url = ""

    def __init__(self, clock=time.monotonic):
        self.stats = {"frames": 0, "corrupt": 0, "errors": 0}
        self.clock = clock
        self._closed = False

    def recv(self, timeout=None):
        """The next TrackerSample or HeadsetSample, or None if none arrived within `timeout` seconds
        (None: wait for one)."""
        if timeout is not None and timeout <= 0.0:     # what has arrived, without waiting (every tick's drain)
            return self._recv_internal(0.0)
        deadline = None if timeout is None else self.clock() + timeout
        while True:
            left = None if deadline is None else max(deadline - self.clock(), 0.0)
            sample = self._recv_internal(left)
            if sample is not None:
                return sample
            if left == 0.0 or (deadline is not None and self.clock() >= deadline):
                return None

    @abstractmethod
    def _recv_internal(self, timeout):
        """One sample, or None if none completed: wait at most `timeout` s (None: as long as it takes)
        for input, and read what is already queued without waiting."""

    @property
    def state(self):
        return CLOSED if self._closed else ACTIVE

    # Optional capabilities, declared here with what a source without them answers (as python-can's
    # BusABC declares send_periodic or state): a transport that has one overrides it.
    def send_pose(self, frame):
        """Send a PoseFrame back over this link (the headset's pose stream). Raises TransportError on a
        link that carries none."""
        raise TransportError(f"{type(self).__name__} carries no pose stream")

    def tell_body(self, shape):
        """The user's body the poses are posed on (a BODY_SHAPE text, firmware_bridge.wire.webxr), for a
        link that draws it (the WebXR page); the others have no use for it."""
        return None

    def link_summary(self):
        """The link's own account (a webxr headset: pairing, wrong codes, refused, frames), or None."""
        return None

    def status_text(self):
        """A few words for the service's status line about the link (empty: nothing to add)."""
        return ""

    def trackers(self):
        """The trackers this link has heard, by id, with what it knows of each ({}: none it names)."""
        return {}

    def close(self):
        """Release the device (once; closing again does nothing)."""
        if not self._closed:
            self._closed = True
            self._close_internal()

    def _close_internal(self):  # noqa: B027 (a hook, not abstract: a transport with nothing to release keeps it)
        """What a transport releases on close (nothing, unless a transport overrides it)."""

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


# ---- URL schemes ----------------------------------------------------------------------------------

SCHEMES = {}          # scheme -> module path (imported when first opened: each brings its own dependency)


def register_scheme(scheme, module):
    """Handle `scheme://` URLs with `module` (a dotted path to a module with open/tracker_names)."""
    SCHEMES[scheme] = module


for _scheme, _module in {"serial": "serial_port", "i2c": "i2c", "can": "can_bus", "slimevr": "slimevr",
                        "webxr": "webxr"}.items():
    register_scheme(_scheme, f"firmware_bridge.transports.{_module}")


def _plugins():
    try:
        found = entry_points(group="edgepose.transports")
    except TypeError:            # Python < 3.10 signature; not ours to support, but not a crash either
        found = ()
    for ep in found:
        SCHEMES.setdefault(ep.name, ep.value)


def parse_url(url):
    """'scheme://netloc/path?k=v' -> (scheme, netloc, path, {k: v}) for a scheme that is registered."""
    p = urlparse(url)
    if p.scheme not in SCHEMES:
        _plugins()
    if p.scheme not in SCHEMES:
        raise TransportError(f"unknown transport in {url!r}: use one of {', '.join(s + '://' for s in SCHEMES)}")
    query = {k: v[-1] for k, v in parse_qs(p.query).items()}
    return p.scheme, p.netloc, p.path, query


def scheme_module(url):
    parsed = parse_url(url)
    return importlib.import_module(SCHEMES[parsed[0]]), parsed


def open_source(url, **kw):
    """The Source a URL names; `kw` go to its scheme's open()."""
    module, parsed = scheme_module(url)
    return module.open(url, parsed, **kw)


def tracker_names(url):
    """The tracker names a source URL declares (its scheme reads its own query)."""
    module, parsed = scheme_module(url)
    return list(module.tracker_names(parsed)) if hasattr(module, "tracker_names") else []


def id_names(text, ids, example):
    """'0:waist,1:l_foot' -> {0: 'waist', 1: 'l_foot'}: the ID:NAME list of a URL query (ids decimal
    or 0x hex, each in `ids`); TransportError with `example` when it is not one."""
    out = {}
    for item in filter(None, (part.strip() for part in (text or "").split(","))):
        wire_id, sep, name = item.partition(":")
        try:
            number = int(wire_id.strip(), 0)
        except ValueError:
            number = None
        if not sep or number not in ids or not name.strip():
            raise TransportError(f"expected ID:NAME pairs with ids {ids.start}-{ids.stop - 1}, such as {example}, "
                                 f"got {text!r}")
        out[number] = name.strip()
    return out
