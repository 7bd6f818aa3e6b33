"""The board's configuration file (TOML or JSON): which sources, which outputs, runtime settings.

    [headset]
    url = "serial:///dev/ttyAMA0?baud=460800&role=headset"

    [[trackers]]                      # one table per IMU source; names come from the URL
    url = "i2c://1/0x28?tracker=waist&rate=100"

    [[trackers]]
    url = "can://socketcan/can0?nodes=1:l_foot,2:r_foot"

    [output]
    pose_stream = "headset"           # POSE_FRAME back over the headset link, or a serial:// URL, or ""
    vmc = "127.0.0.1:39539"           # optional
    vrchat = "127.0.0.1:9000"         # optional
    bvh = "out/take.bvh"              # optional recording

    [runtime]
    samples = 16                      # latent samples N (1..128); with adaptive N, the most it runs
    adaptive = true                   # lower N when frames run late, raise it again when there is slack
    precision = "int8"                # or "fp32"
    lookahead = 0                     # SSI look-ahead in frames: 0 sends the newest frame; each frame more
                                      # puts the body 1/hz later (10 at 60 Hz: 167 ms), for recording only
    hz = 60
    lost_after_ms = 250
    sync_latency_ms = 20              # interpolate this far in the past (>= one headset period)
    calibration = "calibration.json"  # optional, from `edge calibrate`
    models = "models"                 # optional, default: the shipped models
    leg_guard_cm = 16                 # the foot IK keeps a free leg this far from the other (0: off)

    [refine]                          # latent refinement of the shown sample (edge.refine)
    enabled = true                    # the headset's TARGET messages need it; "legs" keeps the legs apart
    steps = 2                         # Gauss-Newton steps a frame (K), the most: adaptive lowers it with N
    terms = ["targets", "keep", "floor", "legs"]   # also "imus" or "imus-tilt"

Every mistake is reported at start-up with the file, the key and what to write instead.
"""
import json
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from edge.inference import DEFAULT_PRECISION
from edge.options import PipelineOptions
from edge.physics import LEG_GUARD_M
from firmware_bridge.transports.base import TransportError, parse_url, tracker_names


class ConfigError(ValueError):
    """A configuration file that cannot be used; the message says what to fix."""


SECTIONS = {
    "headset": {"url"},
    "trackers": {"url"},
    "output": {"pose_stream", "vmc", "vmc_mode", "vrchat", "vrchat_trackers", "bvh"},
    "runtime": {"samples", "adaptive", "precision", "lookahead", "hz", "lost_after_ms", "sync_latency_ms",
                "calibration", "models", "leg_guard_cm"},
    "refine": {"enabled", "steps", "terms"},
    "body": {"height_m", "leg_length_m", "arm_length_m"},
}
REFINE_TERMS = ("targets", "keep", "floor", "legs", "imus", "imus-tilt")


@dataclass
class Config:
    headset: str
    trackers: list
    pose_stream: str = "headset"
    vmc: str = ""
    vrchat: str = ""
    vmc_mode: str = "split"
    vrchat_trackers: tuple = ("pelvis", "chest", "l_ankle", "r_ankle", "l_knee", "r_knee")
    bvh: str = ""
    samples: int = 16
    adaptive: bool = True
    precision: str = DEFAULT_PRECISION
    lookahead: int = 0
    hz: float = 60.0
    lost_after: float = 0.25
    sync_latency: float = 0.02
    calibration: str = ""
    models: str = ""
    leg_guard: float = LEG_GUARD_M  # m; [runtime] leg_guard_cm / 100
    path: str = ""
    tracker_names: list = field(default_factory=list)
    refine: dict = None             # [refine] as RefineSettings' fields (None: off)
    height_m: float = None          # [body] height_m: the user's stature, over the calibration's measured one
    leg_length_m: float = None      # [body] leg_length_m: floor to hip joint standing (edge.proportions)
    arm_length_m: float = None      # [body] arm_length_m: shoulder joint to wrist, over the calibration's

    def pipeline_options(self):
        """The board's Pipeline, as edge.options.PipelineOptions: [runtime]'s N, look-ahead, rate,
        precision and leg guard, and [refine]."""
        return PipelineOptions(samples=self.samples, lookahead=self.lookahead, fps=self.hz, precision=self.precision,
                               refine=self.refine, leg_guard=self.leg_guard)


from edge.imus import TRACKER_NAMES  # noqa: E402  (the body locations a tracker may be named for)


def _host_port(value, where):
    host, sep, port = value.rpartition(":")
    if not sep or not port.isdigit() or not host:
        raise ConfigError(f"{where}: expected HOST:PORT such as 127.0.0.1:39539, got {value!r}")
    return host, int(port)


def tracker_names_of(url):
    """Tracker names a source URL declares, as its scheme reads them: ?tracker=NAME (I2C),
    ?nodes=1:a,2:b (CAN), ?trackers=0:a,1:b (serial hub; without it the waist as id 0),
    ?trackers=MAC/SENSOR:NAME,... (SlimeVR)."""
    try:
        return tracker_names(url)
    except TransportError as e:
        raise ConfigError(str(e)) from None


def load(path):
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as e:
        raise ConfigError(f"cannot read config {path}: {e.strerror}") from None
    try:
        raw = json.loads(text) if path.suffix == ".json" else tomllib.loads(text)
    except (ValueError, tomllib.TOMLDecodeError) as e:
        raise ConfigError(f"{path}: not valid {'JSON' if path.suffix == '.json' else 'TOML'}: {e}") from None
    return from_dict(raw, str(path))


def from_dict(raw, where="config"):
    """A parsed TOML document -> Config, every section checked; the first problem is a ConfigError that
    names the file, the section and what is allowed."""
    check_sections(raw, where)
    if "headset" not in raw or "url" not in raw["headset"]:
        raise ConfigError(f"{where}: [headset] url is required (e.g. serial:///dev/ttyAMA0?role=headset)")
    cfg = Config(headset=raw["headset"]["url"], trackers=[t.get("url") for t in raw.get("trackers", [])], path=where)
    read_devices(cfg, where)
    read_output(cfg, raw.get("output", {}), where)
    read_runtime(cfg, raw.get("runtime", {}), where)
    cfg.refine = refine_section(raw.get("refine", {}), where)
    cfg.height_m, cfg.leg_length_m, cfg.arm_length_m = read_body(raw.get("body", {}), where)
    return cfg


def read_body(body, where):
    """[body] height_m: the user's stature written by hand, which wins over the one the standing
    calibration measured (a headset worn high, a calibration done sitting); leg_length_m: from the
    floor to the hip joint, standing (the bony point at the side of the hip), for legs long or short for
    the height (edge.proportions); arm_length_m: shoulder joint to wrist, over what the T-pose measured.
    -> (height_m, leg_length_m, arm_length_m), None where not given."""
    out = []
    for key, low, high, what in (("height_m", 1.0, 2.3, "the user's height in metres"),
                                 ("leg_length_m", 0.6, 1.3, "floor to hip joint standing, in metres"),
                                 ("arm_length_m", 0.3, 0.9, "shoulder joint to wrist, in metres")):
        v = body.get(key)
        if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float)) or not low <= v <= high):
            raise ConfigError(f"{where}: [body] {key} is {what}, {low:g} to {high:g}; got {v!r}")
        out.append(None if v is None else float(v))
    return tuple(out)


def check_sections(raw, where):
    """Only the known sections, each a table (or a list of them) of its known keys."""
    for key, value in raw.items():
        if key not in SECTIONS:
            raise ConfigError(f"{where}: unknown section [{key}]; sections are {', '.join(sorted(SECTIONS))}")
        for table in (value if isinstance(value, list) else [value]):
            if not isinstance(table, dict):
                raise ConfigError(f"{where}: [{key}] must be a table")
            unknown = set(table) - SECTIONS[key]
            if unknown:
                raise ConfigError(f"{where}: unknown key {sorted(unknown)[0]!r} in [{key}]; "
                                  f"allowed: {', '.join(sorted(SECTIONS[key]))}")


def read_devices(cfg, where):
    """The headset's and trackers' URLs parse, and the trackers they name are the model's, once each."""
    for url, what in [(cfg.headset, "[headset] url")] + [(u, "[[trackers]] url") for u in cfg.trackers]:
        if not isinstance(url, str):
            raise ConfigError(f"{where}: {what} is missing")
        try:
            parse_url(url)
        except TransportError as e:
            raise ConfigError(f"{where}: {what}: {e}") from None
    try:
        cfg.tracker_names = [n for u in cfg.trackers for n in tracker_names_of(u)]
    except ConfigError as e:
        raise ConfigError(f"{where}: [[trackers]] url: {e}") from None
    if len(set(cfg.tracker_names)) != len(cfg.tracker_names):
        raise ConfigError(f"{where}: tracker names repeat: {cfg.tracker_names}")
    unknown = [n for n in cfg.tracker_names if n not in TRACKER_NAMES]
    if unknown:
        raise ConfigError(f"{where}: [[trackers]] url: unknown tracker name {unknown[0]!r}; the model reads "
                          f"{', '.join(TRACKER_NAMES)}")


def read_output(cfg, out, where):
    """[output]: the pose stream, VMC and VRChat's addresses and modes, the BVH file."""
    cfg.pose_stream = out.get("pose_stream", "headset")
    if cfg.pose_stream not in ("headset", "") and not cfg.pose_stream.startswith("serial://"):
        raise ConfigError(f"{where}: [output] pose_stream must be \"headset\", a serial:// URL or \"\"")
    for key in ("vmc", "vrchat"):
        if out.get(key):
            _host_port(out[key], f"{where}: [output] {key}")
            setattr(cfg, key, out[key])
    cfg.vmc_mode = out.get("vmc_mode", cfg.vmc_mode)
    if cfg.vmc_mode not in ("split", "bundle", "messages"):
        raise ConfigError(f"{where}: [output] vmc_mode must be \"split\" (bundles of at most 1,472 bytes: one "
                          f"Ethernet frame each), \"bundle\" (one datagram) or \"messages\", not {cfg.vmc_mode!r}")
    if "vrchat_trackers" in out:
        from edge.skeleton import JOINT_NAMES
        names = out["vrchat_trackers"]
        if (not isinstance(names, list) or not 1 <= len(names) <= 8 or len(set(names)) != len(names)
                or any(n not in JOINT_NAMES for n in names)):
            raise ConfigError(f"{where}: [output] vrchat_trackers is a list of 1 to 8 different joints of "
                              f"{', '.join(JOINT_NAMES)}; got {names!r}")
        cfg.vrchat_trackers = tuple(names)
    cfg.bvh = out.get("bvh", "")


def read_runtime(cfg, rt, where):
    """[runtime]: N, the look-ahead, the rate, the sources' timeouts, the leg guard, precision and files."""
    try:
        cfg.samples = int(rt.get("samples", cfg.samples))
        cfg.lookahead = int(rt.get("lookahead", cfg.lookahead))
        cfg.hz = float(rt.get("hz", cfg.hz))
        cfg.lost_after = float(rt.get("lost_after_ms", 250)) / 1000.0
        cfg.sync_latency = float(rt.get("sync_latency_ms", 20)) / 1000.0
        cfg.leg_guard = float(rt.get("leg_guard_cm", LEG_GUARD_M * 100)) / 100.0
    except (TypeError, ValueError) as e:
        raise ConfigError(f"{where}: [runtime] values must be numbers ({e})") from None
    if not 1 <= cfg.samples <= 128:
        raise ConfigError(f"{where}: [runtime] samples must be 1..128, got {cfg.samples}")
    if not 0 <= cfg.lookahead <= 60 or not 10 <= cfg.hz <= 240 or not 0.02 <= cfg.lost_after <= 5:
        raise ConfigError(f"{where}: [runtime] lookahead 0..60 frames, hz 10..240, lost_after_ms 20..5000")
    if not 0 <= cfg.leg_guard <= 0.3:
        raise ConfigError(f"{where}: [runtime] leg_guard_cm must be 0 (off) to 30, got {cfg.leg_guard * 100:g}; "
                          f"the default, {LEG_GUARD_M * 100:g}, was chosen on val")
    cfg.adaptive = rt.get("adaptive", True)
    if not isinstance(cfg.adaptive, bool):
        raise ConfigError(f"{where}: [runtime] adaptive must be true or false, got {cfg.adaptive!r}")
    cfg.precision = rt.get("precision", DEFAULT_PRECISION)
    if cfg.precision not in ("fp32", "int8"):
        raise ConfigError(f"{where}: [runtime] precision must be \"fp32\" or \"int8\", got {cfg.precision!r}")
    cfg.calibration = rt.get("calibration", "")
    cfg.models = rt.get("models", "")


def refine_section(ref, where):
    """[refine] -> the Pipeline's refine= settings, or None when disabled (on by default)."""
    enabled = ref.get("enabled", True)
    if not isinstance(enabled, bool):
        raise ConfigError(f"{where}: [refine] enabled must be true or false, got {enabled!r}")
    steps = ref.get("steps", 2)
    if not isinstance(steps, int) or isinstance(steps, bool) or not 1 <= steps <= 8:
        raise ConfigError(f"{where}: [refine] steps must be a whole number 1..8, got {steps!r}")
    terms = ref.get("terms", ["targets", "keep", "floor", "legs"])
    if not isinstance(terms, list) or not terms or any(t not in REFINE_TERMS for t in terms):
        raise ConfigError(f"{where}: [refine] terms is a list of {', '.join(REFINE_TERMS)}; got {terms!r}")
    return {"steps": steps, "terms": list(terms)} if enabled else None
