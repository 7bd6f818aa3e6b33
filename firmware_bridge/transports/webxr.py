"""The `webxr` scheme: a standalone headset's own browser is the headset link, nothing to install on it.

    webxr://0.0.0.0:8443                        HTTPS + WebSocket on one port (the default)
    webxr://0.0.0.0:8443?state=/var/lib/edgepose  where the certificate and paired tokens are kept
    webxr://127.0.0.1:8080?tls=0                plain HTTP on loopback only: `adb reverse` over USB-C,
                                                where http://localhost is already a secure context

The board serves one page (webxr_page/, plain ES modules) and a WebSocket on the same port. The page
reads the viewer pose and both grip poses every XR frame and sends them (XR_POSE); the board answers
each pose it makes (XR_BODY) on the same socket, which the page draws as a mirror. Messages:
firmware_bridge/wire/webxr.py, laid out in protocol.md section 9.

Who may connect: the WebSocket's Origin must be the board's own page; the page's first message pairs
with the 6-digit code the board prints at start (and on its status line) or presents a token it was
given then. A wrong code closes the socket with a reason and is counted; five in a minute lock pairing
for a minute. One headset at a time: a second is refused as busy unless the first has been silent for
3 s (the same headset reconnecting, known by its token, takes over at once).

The clock: the board pings the page (CLOCK_PING) and keeps the offset of the round trip with the least
delay in a sliding window (an NTP-style minimum-delay filter, as sync.ClockOffset is for serial); each
XR_POSE's page time is mapped onto the board's clock with it before it becomes a HeadsetSample.

The server is an asyncio loop in its own thread; decoded samples reach the service through
Source.recv (a queue), so nothing here ever waits on the tick or the tick on a socket.
"""
import asyncio
import hashlib
import hmac
import importlib
import ipaddress
import json
import os
import queue
import secrets
import socket
import ssl
import sys
import threading
import time
from collections import deque
from datetime import datetime, timedelta, timezone
from pathlib import Path

import numpy as np

from firmware_bridge.transports.base import Source, TransportError
from firmware_bridge.wire import webxr as wire
from firmware_bridge.wire.framing import ProtocolError
from firmware_bridge.wire.messages import POSE_RECORD, pose_record

PAGE_DIR = Path(__file__).resolve().parent / "webxr_page"
PAGE_FILES = {"/": ("index.html", "text/html; charset=utf-8"),
              "/index.html": ("index.html", "text/html; charset=utf-8"),
              "/app.js": ("app.js", "text/javascript; charset=utf-8"),
              "/wire.js": ("wire.js", "text/javascript; charset=utf-8"),
              "/mirror.js": ("mirror.js", "text/javascript; charset=utf-8"),
              "/skeleton.js": ("skeleton.js", "text/javascript; charset=utf-8")}
SOCKET_PATH = "/socket"
QUERY_KEYS = {"state", "tls"}

HELLO_TIMEOUT_S = 10.0          # an opened socket that says nothing this long is closed
BUSY_SILENCE_S = 3.0            # a connected headset silent this long may be replaced by another
WRONG_CODES_TO_LOCK = 5
WRONG_CODE_WINDOW_S = 60.0
LOCK_S = 60.0
MAX_UNPAIRED = 8                # sockets waiting for their HELLO at once; more are refused
MAX_MESSAGE = 64 * 1024         # websockets closes a connection sending more in one message (1009)
MAX_QUEUE = 4096                # decoded samples the tick has not taken yet
MESSAGES_PER_S = 600            # a paired headset sends ~72-120 XR_POSE a second; more is a flood, dropped
SEND_BUFFER_LIMIT = 64 * 1024   # a page this far behind reading its poses gets none until it catches up
MAX_TOKENS = 32                 # headsets remembered; the oldest is forgotten (it pairs again)
PING_FAST_S, PING_S = 0.1, 0.5  # clock pings: quickly for the first second of a connection, then steady

# WebSocket close codes (4000-4999: the application's own); the page shows the reason.
CLOSE_NO_HELLO, CLOSE_WRONG_CODE, CLOSE_UNKNOWN_TOKEN, CLOSE_LOCKED = 4000, 4001, 4002, 4003
CLOSE_REPLACED, CLOSE_BUSY, CLOSE_TOO_MANY = 4008, 4009, 4029


def default_state_dir():
    """$EDGEPOSE_STATE_DIR, else $XDG_STATE_HOME/edgepose, else ~/.local/state/edgepose."""
    if os.environ.get("EDGEPOSE_STATE_DIR"):
        return Path(os.environ["EDGEPOSE_STATE_DIR"])
    base = os.environ.get("XDG_STATE_HOME") or Path.home() / ".local" / "state"
    return Path(base) / "edgepose"


def tracker_names(parsed):
    return []


def open(url, parsed, clock=time.monotonic, announce="stderr", **_):
    """Source for 'webxr://HOST:PORT?state=DIR&tls=0|1'; fails at start-up with the fix. `announce`: where
    the page's address, the fingerprint and the pairing code are printed (None: nowhere)."""
    try:
        for name in ("websockets", "cryptography"):       # only this scheme needs them: imported when opened
            importlib.import_module(name)
    except ImportError as e:
        raise TransportError(f"{url!r} needs the [headset] extra ({e.name or name} is missing): "
                             f"pip install 'edgepose[headset]' (on a board: /opt/edgepose/venv/bin/pip install "
                             f"'edgepose[headset]'; from a checkout: .venv/bin/pip install -e '.[headset]')") from None
    _, netloc, path, query = parsed
    host, sep, port = netloc.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 <= int(port) <= 65535 or path not in ("", "/"):
        raise TransportError(f"{url!r}: expected webxr://HOST:PORT such as webxr://0.0.0.0:8443")
    unknown = set(query) - QUERY_KEYS
    if unknown:
        raise TransportError(f"{url!r}: unknown option {sorted(unknown)[0]!r}; webxr:// takes "
                             f"{', '.join(sorted(QUERY_KEYS))}")
    tls = query.get("tls", "1")
    if tls not in ("0", "1"):
        raise TransportError(f"{url!r}: tls must be 1 (HTTPS, the default) or 0, not {tls!r}")
    if tls == "0" and host not in ("127.0.0.1", "localhost", "::1"):
        raise TransportError(f"{url!r}: plain HTTP (tls=0) only on 127.0.0.1, for `adb reverse` over USB-C; a "
                             f"headset's browser allows WebXR on http:// from localhost only. Drop tls=0 to serve "
                             f"HTTPS on {host}")
    state = Path(query["state"]).expanduser() if query.get("state") else default_state_dir()
    return WebXRSource(host.strip("[]"), int(port), state, tls=tls == "1", clock=clock, url=url, announce=announce)


# ---- the certificate and the paired tokens, kept in the state folder -------------------------------

def local_addresses():
    """This board's IPv4 addresses a headset may reach it at (the default route's first)."""
    found = []
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
            probe.connect(("192.0.2.1", 9))          # TEST-NET: no packet leaves, the route picks the address
            found.append(probe.getsockname()[0])
    except OSError:
        pass
    try:
        found += socket.gethostbyname_ex(socket.gethostname())[2]
    except OSError:
        pass
    return [a for a in dict.fromkeys(found) if not a.startswith("127.")]


def ensure_certificate(folder, host):
    """(cert path, key path, SHA-256 fingerprint 'AB:CD:..'), made once and kept: the headset's browser
    remembers the exception the user granted for it, so it must not change at each start."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID
    cert_path, key_path = folder / "webxr-cert.pem", folder / "webxr-key.pem"
    if not (cert_path.exists() and key_path.exists()):
        name = socket.gethostname()
        key = ec.generate_private_key(ec.SECP256R1())
        ips = {"127.0.0.1", *local_addresses()}
        try:
            ips.add(str(ipaddress.ip_address(host)))
        except ValueError:
            pass
        ips.discard("0.0.0.0")
        alt = [x509.DNSName("localhost"), x509.DNSName(name), x509.DNSName(f"{name}.local")]
        alt += [x509.IPAddress(ipaddress.ip_address(a)) for a in sorted(ips)]
        subject = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, f"edgepose {name}")])
        now = datetime.now(timezone.utc)
        cert = (x509.CertificateBuilder().subject_name(subject).issuer_name(subject).public_key(key.public_key())
                .serial_number(x509.random_serial_number()).not_valid_before(now - timedelta(days=1))
                .not_valid_after(now + timedelta(days=3650))
                .add_extension(x509.SubjectAlternativeName(alt), critical=False)
                .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
                .sign(key, hashes.SHA256()))
        write_private(key_path, key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                                  serialization.NoEncryption()))
        cert_path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    return cert_path, key_path, fingerprint(cert_path.read_bytes())


def fingerprint(pem):
    """SHA-256 of a PEM certificate's DER bytes, as browsers show it (AB:CD:...)."""
    der = ssl.PEM_cert_to_DER_cert(pem.decode() if isinstance(pem, bytes) else pem)
    return ":".join(f"{b:02X}" for b in hashlib.sha256(der).digest())


def write_private(path, data):
    """Write a file only its owner can read, replacing it atomically."""
    tmp = path.with_suffix(".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(data)
    os.replace(tmp, path)


class TokenStore:
    """The headsets paired with this board: a SHA-256 of each token (the token itself stays in the
    headset's browser), newest last, in tokens.json. Delete the file to forget them all."""

    def __init__(self, path):
        self.path = path
        try:
            self.hashes = [h for h in json.loads(path.read_text()).get("tokens", []) if isinstance(h, str)]
        except (OSError, ValueError, AttributeError):
            self.hashes = []

    @staticmethod
    def digest(token):
        return hashlib.sha256(token.encode()).hexdigest()

    def knows(self, token):
        wanted = self.digest(token)
        return any(hmac.compare_digest(wanted, h) for h in self.hashes)

    def issue(self):
        token = secrets.token_hex(16)
        self.hashes = (self.hashes + [self.digest(token)])[-MAX_TOKENS:]
        write_private(self.path, json.dumps({"tokens": self.hashes}).encode())
        return token


class PageClock:
    """Board-minus-page clock offset (ms): the offset of the ping round trip with the least delay among
    the last `window` (at PING_S, the last 16 s), its midpoint taken as when the page read its clock."""

    def __init__(self, window=32):
        self.rtt = deque(maxlen=window)
        self.offsets = deque(maxlen=window)

    def add(self, sent_ms, page_ms, now_ms):
        self.rtt.append(now_ms - sent_ms)
        self.offsets.append((sent_ms + now_ms) / 2.0 - page_ms)

    @property
    def offset_ms(self):
        if not self.rtt:
            return None
        return self.offsets[min(range(len(self.rtt)), key=self.rtt.__getitem__)]

    @property
    def best_rtt_ms(self):
        return min(self.rtt) if self.rtt else None


class Headset:
    """One paired connection."""

    def __init__(self, ws, token, now):
        self.ws, self.token = ws, token
        self.connected_at = self.last_heard = now
        self.clock = PageClock()
        self.pings = deque(maxlen=16)        # board times (ms) of the pings not yet answered
        self.newest_page_ms = 0.0            # the newest XR_POSE's page time, echoed in XR_BODY
        self.frames = 0
        self.window_start, self.window_count = now, 0   # the flood guard's one-second window
        self.rate = deque(maxlen=128)        # arrival times of the last XR_POSEs, for the status line


class WebXRSource(Source):
    """HeadsetSamples from the board's own page in a headset's browser, and the body back to it."""

    def __init__(self, host, port, state_dir, tls=True, clock=time.monotonic, url="", announce="stderr"):
        super().__init__(clock)
        self.url = url or f"webxr://{host}:{port}"
        self.stats.update({"missed": 0, "sent": 0, "send_dropped": 0, "connections": 0, "paired": 0,
                           "wrong_code": 0, "refused_locked": 0, "refused_busy": 0, "refused_origin": 0,
                           "unknown_token": 0, "no_hello": 0, "too_many": 0, "flood": 0, "unsynced": 0,
                           "replaced": 0, "oversize": 0, "queue_full": 0})
        self.code = f"{secrets.randbelow(10 ** wire.CODE_DIGITS):0{wire.CODE_DIGITS}d}"
        self.tls, self.scheme = tls, "https" if tls else "http"
        try:
            state_dir.mkdir(parents=True, exist_ok=True, mode=0o700)
            self.tokens = TokenStore(state_dir / "webxr-tokens.json")
            self.cert_path, self.key_path, self.fingerprint = ensure_certificate(state_dir, host) if tls else \
                (None, None, None)
        except OSError as e:
            raise TransportError(f"{self.url}: cannot keep the headset link's certificate and tokens in {state_dir}: "
                                 f"{e.strerror or e}; give a writable folder with ?state=DIR (or "
                                 f"EDGEPOSE_STATE_DIR)") from None
        self.state_dir = state_dir
        self.busy_silence_s = BUSY_SILENCE_S
        self._samples = queue.SimpleQueue()
        self._headset = None
        self._unpaired = 0
        self._wrong_codes = deque()
        self._locked_until = -float("inf")
        self._seq = 0
        self._shape = None                    # the BODY_SHAPE text the page gets after WELCOME (tell_body)
        # One XR_BODY buffer, its POSE_FRAME payload a numpy view into it: a pose is written in place.
        self._body = bytearray(wire.XR_BODY_SIZE)
        self._record = np.frombuffer(self._body, POSE_RECORD, count=1, offset=wire.XR_BODY_HEADER.size).reshape(())
        self.last_close = ""                  # why the last refused or closed socket was closed
        self._loop = None
        self._stop = None
        self._started = threading.Event()
        self._start_error = None
        self._thread = threading.Thread(target=self._serve_forever, args=(host, port), daemon=True,
                                        name=f"edge webxr {host}:{port}")
        self._thread.start()
        self._started.wait(10.0)
        if self._start_error is not None or self._loop is None:
            self._thread.join(1.0)
            raise TransportError(f"cannot serve the headset page on {host}:{port}: {self._start_error}; is another "
                                 f"program using the port, or the address not this board's?")
        self.port = self.address[1]
        if announce is not None:
            self.announce(sys.stderr if announce == "stderr" else announce)

    # ---- what a person reads at start-up and on the status line -------------------------------------
    def page_urls(self):
        host = self.address[0]
        hosts = local_addresses() or ["<board>"] if host in ("0.0.0.0", "::") else [host]
        return [f"{self.scheme}://{h}:{self.port}/" for h in hosts]

    def announce(self, out):
        print(f"edge run: headset page: open {' or '.join(self.page_urls())} in the headset's browser", file=out)
        if self.fingerprint:
            print(f"edge run: its certificate's SHA-256 fingerprint: {self.fingerprint}", file=out)
        print(f"edge run: pairing code {self.code}", file=out, flush=True)

    def status_text(self):
        """'webxr: 72/s rtt 1 ms | code 123456' (the headset's rate, the socket's round trip, how to pair) for
        `edge run`'s status line."""
        h, now = self._headset, self.clock()
        if now < self._locked_until:
            pairing = f"pairing locked {self._locked_until - now:.0f} s"
        else:
            pairing = f"code {self.code}"
        if h is None:
            return f"webxr: waiting for a headset | {pairing}"
        rtt = h.clock.best_rtt_ms
        return (f"webxr: {self._rate(h, now):.0f}/s rtt {'-' if rtt is None else f'{rtt:.0f}'} ms"
                f"{' silent' if now - h.last_heard > 1.0 else ''} | {pairing}")

    def link_summary(self):
        h = self._headset
        return {"connected": h is not None, "pairing_code": self.code, "fingerprint": self.fingerprint,
                "clock_offset_ms": None if h is None else h.clock.offset_ms,
                "rtt_ms": None if h is None else h.clock.best_rtt_ms, "last_close": self.last_close,
                **{k: self.stats[k] for k in ("connections", "paired", "wrong_code", "refused_locked",
                                               "refused_busy", "refused_origin", "unknown_token", "flood",
                                               "send_dropped", "replaced", "oversize")}}

    @staticmethod
    def _rate(h, now):
        recent = [t for t in h.rate if now - t <= 1.0]
        return len(recent) / min(1.0, max(now - h.connected_at, 1e-3)) if recent else 0.0

    @property
    def clock_offset_ms(self):
        """Board clock (self.clock, ms) minus the connected page's clock, or None."""
        h = self._headset
        return None if h is None else h.clock.offset_ms

    # ---- the Source interface -------------------------------------------------------------------------
    def _recv_internal(self, timeout):
        try:
            if timeout is None or timeout > 0:
                return self._samples.get(timeout=timeout)
            return self._samples.get_nowait()
        except queue.Empty:
            return None

    def send_pose(self, frame):
        """Hand one PoseFrame to the connected page (False when there is none). Never waits: the socket's
        thread sends it, or drops it (counted) when the page is not keeping up."""
        h, loop = self._headset, self._loop
        if h is None or loop is None:
            return False
        pose_record(frame, self._record)
        # The page time the body stands for: the newest XR_POSE the board had, less any look-ahead the
        # frame was held for, so the page's "lag" is what the user sees (docs/headset.md).
        wire.XR_BODY_HEADER.pack_into(self._body, 0, wire.XR_BODY, 0, self._seq,
                                      h.newest_page_ms - 1000.0 * frame.held_s)
        self._seq = (self._seq + 1) & 0xFFFF
        loop.call_soon_threadsafe(self._send_body, h, bytes(self._body))
        return True

    def tell_body(self, shape):
        """The body the poses are posed on, as a BODY_SHAPE text (wire.encode_body_shape): the connected
        page gets it now, and every page that pairs after it, right after WELCOME."""
        self._shape = shape
        h, loop = self._headset, self._loop
        if h is not None and loop is not None:
            loop.call_soon_threadsafe(self._send_shape, h, shape)

    def _close_internal(self):
        if self._loop is not None and self._stop is not None:
            self._loop.call_soon_threadsafe(self._stop.set)
        self._thread.join(5.0)

    # ---- the server thread ----------------------------------------------------------------------------
    def _serve_forever(self, host, port):
        try:
            asyncio.run(self._main(host, port))
        except Exception as e:             # start-up failure: reported by the constructor
            if self._start_error is None:
                self._start_error = f"{type(e).__name__}: {e}"
            self._started.set()

    async def _main(self, host, port):
        from websockets.asyncio.server import serve
        context = None
        if self.tls:
            context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
            context.minimum_version = ssl.TLSVersion.TLSv1_2
            context.load_cert_chain(self.cert_path, self.key_path)
        self._stop = asyncio.Event()
        try:
            server = await serve(self._handle, host, port, ssl=context, process_request=self._http,
                                 max_size=MAX_MESSAGE, max_queue=64, compression=None, server_header=None,
                                 ping_interval=1.0, ping_timeout=5.0, close_timeout=1.0)
        except OSError as e:
            self._start_error = e.strerror or str(e)
            self._started.set()
            return
        self.address = server.sockets[0].getsockname()[:2]
        self._loop = asyncio.get_running_loop()
        self._started.set()
        async with server:
            await self._stop.wait()
            server.close(close_connections=True)

    def _http(self, connection, request):
        """The page's files for plain GETs; for the WebSocket upgrade, the Origin check."""
        from websockets.datastructures import Headers
        from websockets.http11 import Response
        path = request.path.split("?", 1)[0]
        one = lambda name: (lambda values: values[0] if len(values) == 1 else None)(request.headers.get_all(name))
        if any(value.lower() == "websocket" for value in request.headers.get_all("Upgrade")):
            host, origin = one("Host"), one("Origin")        # a repeated header is as bad as a missing one
            if path != SOCKET_PATH or host is None or origin != f"{self.scheme}://{host}":
                self.stats["refused_origin"] += 1
                self.last_close = f"refused a socket from origin {origin!r} for {host!r}"
                return connection.respond(403, "This socket serves the board's own page only.\n")
            return None
        if path not in PAGE_FILES:
            return connection.respond(404, "Not found. The headset page is /\n")
        name, kind = PAGE_FILES[path]
        body = (PAGE_DIR / name).read_bytes()
        headers = Headers([("Content-Type", kind), ("Content-Length", str(len(body))), ("Cache-Control", "no-cache"),
                           ("X-Content-Type-Options", "nosniff"), ("Referrer-Policy", "no-referrer"),
                           ("Content-Security-Policy", "default-src 'self'; connect-src 'self'; "
                                                       "style-src 'self' 'unsafe-inline'; frame-ancestors 'none'")])
        return Response(200, "OK", headers, body)

    def _refuse(self, ws, code, reason, counter):
        self.stats[counter] += 1
        self.last_close = f"{code} {reason}"
        return ws.close(code, reason)

    async def _handle(self, ws):
        """One socket: the HELLO, then the paired headset's messages until it closes."""
        self.stats["connections"] += 1
        if self._unpaired >= MAX_UNPAIRED:
            await self._refuse(ws, CLOSE_TOO_MANY, "too many connections waiting to pair", "too_many")
            return
        self._unpaired += 1
        try:
            headset = await self._pair(ws)
        finally:
            self._unpaired -= 1
        if headset is None:
            return
        pinger = asyncio.ensure_future(self._ping(headset))
        try:
            async for message in ws:
                try:
                    self._on_message(headset, message)
                except Exception as e:     # a bug of ours must not end the link: count it, go on
                    self.stats["errors"] += 1
                    self.last_error = f"{type(e).__name__}: {e}"
        except Exception as e:             # a WebSocket protocol error or a dropped connection: it just ends
            if getattr(getattr(e, "sent", None), "code", None) == 1009:
                self.stats["oversize"] += 1      # a message beyond MAX_MESSAGE: websockets closed the link
                self.last_close = "1009 a message beyond 64 KiB"
        finally:
            pinger.cancel()
            if self._headset is headset:
                self._headset = None

    async def _pair(self, ws):
        from websockets.exceptions import ConnectionClosed
        try:
            first = await asyncio.wait_for(ws.recv(), HELLO_TIMEOUT_S)
        except (asyncio.TimeoutError, ConnectionClosed):
            self.stats["no_hello"] += 1
            await ws.close(CLOSE_NO_HELLO, "no HELLO")
            return None
        try:
            if not isinstance(first, str):
                raise ProtocolError("the first message must be the HELLO (text)")
            kind, value = wire.decode_hello(first)
        except ProtocolError as e:
            self._count_corrupt(e)
            await self._refuse(ws, CLOSE_NO_HELLO, "expected a HELLO with the pairing code or a token", "no_hello")
            return None
        now = self.clock()
        if kind == "code":
            if now < self._locked_until:
                await self._refuse(ws, CLOSE_LOCKED, f"pairing is locked for {self._locked_until - now:.0f} s after "
                                                     f"{WRONG_CODES_TO_LOCK} wrong codes", "refused_locked")
                return None
            if not hmac.compare_digest(value, self.code):
                self._wrong_codes.append(now)
                while self._wrong_codes and now - self._wrong_codes[0] > WRONG_CODE_WINDOW_S:
                    self._wrong_codes.popleft()
                if len(self._wrong_codes) >= WRONG_CODES_TO_LOCK:
                    self._locked_until = now + LOCK_S
                    self._wrong_codes.clear()
                await self._refuse(ws, CLOSE_WRONG_CODE, "wrong pairing code", "wrong_code")
                return None
        elif not self.tokens.knows(value):
            await self._refuse(ws, CLOSE_UNKNOWN_TOKEN, "this board does not know this headset: pair again with "
                                                        "the code", "unknown_token")
            return None
        current = self._headset
        token = value if kind == "token" else None
        if current is not None:
            same = token is not None and current.token == token
            if not same and now - current.last_heard < self.busy_silence_s:
                await self._refuse(ws, CLOSE_BUSY, "busy: another headset is connected", "refused_busy")
                return None
            self.stats["replaced"] += 1
            asyncio.ensure_future(current.ws.close(CLOSE_REPLACED, "replaced by a newer connection"))
        if token is None:
            token = self.tokens.issue()
        headset = Headset(ws, token, now)
        self._headset = headset
        self.stats["paired"] += 1
        try:
            await ws.send(json.dumps({"welcome": 1, "token": token, "board": socket.gethostname()}))
            if self._shape is not None:
                await ws.send(self._shape)
        except ConnectionClosed:
            return None
        return headset

    async def _ping(self, headset):
        """Clock pings: fast while the offset is new, then steady."""
        from websockets.exceptions import ConnectionClosed
        try:
            while True:
                board_ms = self.clock() * 1000.0
                headset.pings.append(board_ms)
                await headset.ws.send(wire.encode_clock_ping(board_ms))
                fast = self.clock() - headset.connected_at < 1.0
                await asyncio.sleep(PING_FAST_S if fast else PING_S)
        except ConnectionClosed:
            pass

    def _send_body(self, headset, data):
        if headset is not self._headset:
            return
        transport = headset.ws.transport
        if transport is None or transport.is_closing() or transport.get_write_buffer_size() > SEND_BUFFER_LIMIT:
            self.stats["send_dropped"] += 1
            return
        asyncio.ensure_future(self._send(headset, data))

    def _send_shape(self, headset, shape):
        """Never dropped for a full buffer, as a body is: the page would draw the wrong body until it
        reconnected."""
        if headset is self._headset:
            asyncio.ensure_future(self._send_text(headset, shape))

    @staticmethod
    async def _send_text(headset, text):
        try:
            await headset.ws.send(text)
        except Exception:                    # closed under us: the page reconnects and gets it after WELCOME
            pass

    async def _send(self, headset, data):
        try:
            await headset.ws.send(data)
            self.stats["sent"] += 1
        except Exception:                    # closed under us: the page reconnects
            self.stats["send_dropped"] += 1

    def _count_corrupt(self, error):
        self.stats["corrupt"] += 1
        key = f"corrupt_{error.kind}"
        self.stats[key] = self.stats.get(key, 0) + 1
        self.last_error = str(error)

    def _on_message(self, h, data):
        """One message from the paired page: decoded, or counted and dropped."""
        now = self.clock()
        h.last_heard = now
        if now - h.window_start >= 1.0:
            h.window_start, h.window_count = now, 0
        h.window_count += 1
        if h.window_count > MESSAGES_PER_S:
            self.stats["flood"] += 1
            return
        if isinstance(data, str):
            self._count_corrupt(ProtocolError("text message after the HELLO"))
            return
        if len(data) > wire.XR_BODY_SIZE:
            self.stats["oversize"] += 1
            self._count_corrupt(ProtocolError(f"{len(data)}-byte message, longer than any this link carries"))
            return
        try:
            kind = wire.message_type(data)
            if kind == wire.XR_POSE:
                self._on_pose(h, data, now)
            elif kind == wire.CLOCK_PONG:
                board_ms, page_ms = wire.decode_clock_pong(data)
                if board_ms not in h.pings:
                    raise ProtocolError("CLOCK_PONG answers no ping this board sent", "value")
                h.pings.remove(board_ms)
                h.clock.add(board_ms, page_ms, now * 1000.0)
            else:
                raise ProtocolError(f"unknown message type {kind:#04x}")
        except ProtocolError as e:
            self._count_corrupt(e)

    def _on_pose(self, h, data, now):
        seq, page_ms, sample = wire.decode_xr_pose(data)
        offset = h.clock.offset_ms
        if offset is None:                 # no clock yet (the first ping is in flight): no time to give it
            self.stats["unsynced"] += 1
            return
        if h.frames:
            gap = (seq - h.last_seq - 1) & 0xFFFF
            self.stats["missed"] += gap if gap < 0x8000 else 0
        h.last_seq = seq
        h.frames += 1
        h.rate.append(now)
        h.newest_page_ms = max(h.newest_page_ms, page_ms)
        sample.t = (page_ms + offset) / 1000.0
        sample.received = now
        if self._samples.qsize() >= MAX_QUEUE:         # the tick has stopped taking them: keep memory bounded
            self.stats["queue_full"] += 1
            return
        self.stats["frames"] += 1
        self._samples.put(sample)
