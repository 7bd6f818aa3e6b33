"""The parts of `edge run` made from its config, each start-up problem said once and the service
carried on: a device that is not there is waited for, a setting that changes nothing is named."""
from edge.governor import SampleGovernor
from firmware_bridge.config import ConfigError
from firmware_bridge.links import REOPEN_AFTER_S, Link


def open_links(cfg, opener, say):
    """The headset's Link, then one per tracker source; a source that is not there yet is retried."""
    links = [Link(cfg.headset, opener)] + [Link(u, opener, required=False) for u in cfg.trackers]
    if links[0].start_error:
        say(f"headset {links[0].url}: {links[0].start_error}; waiting for it (retrying every "
            f"{REOPEN_AFTER_S:g} s; no poses until it sends)")
    for link in links[1:]:
        if link.start_error:
            say(f"{link.url}: {link.start_error}; carrying on without it and retrying")
    return links


def make_governor(cfg):
    """Adaptive N and K (edge.governor): lowered when ticks run late, raised when there is slack (K costs
    only while a target is live); None when the config fixes them."""
    steps = cfg.refine["steps"] if cfg.refine else 0
    if cfg.adaptive and (cfg.samples > 1 or steps):
        return SampleGovernor(1000.0 / cfg.hz, cfg.samples, max_steps=steps)
    return None


def status_printer(status):
    """say(text): 'edge run: text' on the status stream, or nothing without one."""
    if status is None:
        return lambda text: None
    return lambda text: print(f"edge run: {text}", file=status)


def user_body(cfg, calibration):
    """The user's limbs (edge.proportions.UserBody) at the calibration's size: each from a [body]
    leg_length_m / arm_length_m in the config, else from what edge calibrate measured (the arms in the
    T-pose, the legs with --legs); the canonical ones where neither says. A length no skeleton has
    fails with how to measure it."""
    from edge.proportions import UserBody, arms_for, legs_for
    scale = calibration.height_scale
    leg = cfg.leg_length_m or calibration.leg_length_m
    legs = legs_for(leg, scale) if leg else 1.0
    arm = cfg.arm_length_m or calibration.arm_length_m
    arms = arms_for(arm, scale) if arm else 1.0
    try:
        return UserBody(legs, arms)
    except ValueError as e:
        raise ConfigError(f"{cfg.path or 'config'}: on a body {calibration.stature_m():.2f} m tall, {e}: measure "
                          "the legs from the floor to the bony point at the side of the hip, standing, and the "
                          "arm from the shoulder joint to the wrist (or run edge calibrate again)") from None


def load_calibration(cfg):
    """The standing calibration the config names (none: the canonical body), with a [body] height_m
    written in the config winning over the height it measured."""
    from edge.calibration import Calibration
    cal = Calibration.load(cfg.calibration) if cfg.calibration else Calibration()
    return cal.with_stature(cfg.height_m) if cfg.height_m else cal
