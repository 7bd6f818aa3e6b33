"""The transport interface and the URL opener."""
import importlib
from abc import ABC, abstractmethod
from urllib.parse import parse_qs, urlparse


class TransportError(RuntimeError):
    """A source that cannot be opened or has failed for good; the message says what to check."""


class Source(ABC):
    """A device link that yields timestamped samples. Implementations never raise on one bad frame:
    they count it in `stats` and carry on."""

    url = ""

    def __init__(self):
        self.stats = {"frames": 0, "corrupt": 0, "errors": 0}

    @abstractmethod
    def recv(self, timeout=None):
        """The next TrackerSample or HeadsetSample, or None if nothing arrived within `timeout` seconds."""

    def close(self):
        """Release the device."""

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


# scheme -> module under firmware_bridge.transports that defines `open(url, parsed, **kw) -> Source`
SCHEMES = {"serial": "serial_port", "i2c": "i2c", "can": "can_bus", "slimevr": "slimevr"}


def parse_url(url):
    """'scheme://netloc/path?k=v' -> (scheme, netloc, path, {k: v})."""
    p = urlparse(url)
    if p.scheme not in SCHEMES:
        raise TransportError(f"unknown transport in {url!r}: use one of {', '.join(s + '://' for s in SCHEMES)}")
    query = {k: v[-1] for k, v in parse_qs(p.query).items()}
    return p.scheme, p.netloc, p.path, query


def open_source(url, **kw):
    scheme, *_ = parse_url(url)
    module = importlib.import_module(f"firmware_bridge.transports.{SCHEMES[scheme]}")
    return module.open(url, parse_url(url), **kw)
