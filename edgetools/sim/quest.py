"""An emulated Meta Quest 3 for the webxr:// headset link: the board's real page in headless Chromium, with
iwer (Meta's WebXR emulation runtime, MIT, from npm) standing in for the headset, its head and grip
poses following a take at the headset's 72 Hz.

    quest = EmulatedQuest(take)                     # or EmulatedQuest.missing() -> why it cannot run here
    quest.open(source.page_urls()[0]); quest.pair(source.code)
    quest.play(origin_page_ms); quest.enter("immersive-vr")
    quest.state()                                   # the page's window.edgepose
    quest.close()

The page is served by the board unchanged; an init script imports the emulator's module (iwer itself
served from node_modules through Playwright's request routing), which puts iwer's XRSystem on
navigator.xr before the page is paired and offers Enter VR. A 72 Hz display clock drives iwer's frame loop (headless Chromium's own runs at 60 Hz),
and before each frame the head and both grips are set to the take at that moment on the board's session
clock (`play`): the same take `edge replay` plays over the serial link. Each frame's scripted pose is
logged against the sequence number the page sent it with, so a test can hold the board's decoded poses to it.

Chromium is Debian's (/usr/bin/chromium); Playwright's own browser downloads are not used. The headset is
another device, not a second job for the board: for the replay (QuestHeadset), on a machine with more
than one core, the browser and Playwright's driver are kept to the last core at a lower priority, so drawing the page does not take the
board's frame time (on two cores, sharing them made the board late 22-47 times in 10 s and its MPJPE
1.1-1.6x the serial link's).
"""
import importlib
import json
import os
import shutil
from pathlib import Path

import numpy as np

CHROMIUM = os.environ.get("EDGEPOSE_CHROMIUM", "/usr/bin/chromium")
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync",
                 "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-certificate-errors"]
ROOT = Path(__file__).resolve().parents[2]
NPM_CACHE = Path(os.environ.get("EDGEPOSE_NPM_CACHE", ROOT / ".cache" / "npm"))
IWER = NPM_CACHE / "node_modules" / "iwer" / "build" / "iwer.module.js"
EMULATOR_PATH = "/__emulator__/"

# The emulator's module: iwer's Quest 3 on navigator.xr, a 72 Hz frame clock, the take's poses each frame.
# Orientations go from edgepose's convention (faces +Z) to WebXR's (looks down -Z): q * (0,0,-1,0), the
# inverse of what the page does, so the page's message carries the take's quaternion exactly.
DRIVER_JS = r"""
import { XRDevice, metaQuest3, P_SPACE } from "/__emulator__/iwer.module.js";
const device = new XRDevice(metaQuest3);
device.installRuntime({ forceInstall: true });      // desktop Chromium has its own (deviceless) navigator.xr
for (const hand of ["left", "right"]) {          // grips exactly where the take's wrists are
  const grip = device.controllers[hand].inputSource.gripSpace;
  grip[P_SPACE].offsetMatrix.set([1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]);
}
const quest = window.__quest = { device, hz: __HZ__, origin: null, take: null, frames: 0, log: [], lastSeq: null };
fetch("/__emulator__/take.json").then((r) => r.json()).then((take) => { quest.take = take; });

function lerpInto(out, a, i0, i1, w, n) { for (let k = 0; k < n; k++) out[k] = a[i0 * n + k] * (1 - w) + a[i1 * n + k] * w; }
function nlerpInto(out, a, i0, i1, w) {
  let dot = 0; for (let k = 0; k < 4; k++) dot += a[i0 * 4 + k] * a[i1 * 4 + k];
  const s = dot < 0 ? -1 : 1; let n = 0;
  for (let k = 0; k < 4; k++) { out[k] = a[i0 * 4 + k] * (1 - w) + s * a[i1 * 4 + k] * w; n += out[k] * out[k]; }
  n = Math.sqrt(n); for (let k = 0; k < 4; k++) out[k] /= n;
}
const headPos = new Float64Array(3), headRot = new Float64Array(4), handPos = new Float64Array(6), handRot = new Float64Array(8);
const tmp = new Float64Array(4);
function setPose(target, pos, rot) {             // rot: edgepose (w,x,y,z); WebXR's is rot * (0,0,-1,0)
  target.position.set(pos[0], pos[1], pos[2]);
  target.quaternion.set(rot[3], -rot[0], -rot[1], rot[2]);   // (w,x,y,z) = (y, z, -w, -x), set as (x, y, z, w)
}
function script(now) {
  const take = quest.take;
  if (!take || quest.origin === null) return null;
  const x = Math.min(Math.max((now - quest.origin) / 1000 * take.fps, 0), take.frames - 1);
  const i0 = Math.floor(x), i1 = Math.min(i0 + 1, take.frames - 1), w = x - i0;
  lerpInto(headPos, take.head_pos, i0, i1, w, 3); nlerpInto(headRot, take.head_rot, i0, i1, w);
  for (let h = 0; h < 2; h++) {
    lerpInto(tmp, take.hand_pos, 2 * i0 + h, 2 * i1 + h, w, 3); handPos.set(tmp.subarray(0, 3), 3 * h);
    nlerpInto(tmp, take.hand_rot, 2 * i0 + h, 2 * i1 + h, w); handRot.set(tmp, 4 * h);
  }
  setPose(device, headPos, headRot);
  setPose(device.controllers.left, handPos.subarray(0, 3), handRot.subarray(0, 4));
  setPose(device.controllers.right, handPos.subarray(3, 6), handRot.subarray(4, 8));
  return { head_pos: Array.from(headPos), head_rot: Array.from(headRot), hand_pos: Array.from(handPos),
           hand_rot: Array.from(handRot) };
}

// The Quest's display clock: iwer runs one XR frame per window.requestAnimationFrame.
const period = 1000 / quest.hz;
let pending = [], next = performance.now() + period;
window.requestAnimationFrame = (callback) => { pending.push(callback); return pending.length; };
window.cancelAnimationFrame = () => {};
function vsync() {
  const now = performance.now();
  if (now >= next) {
    next = now - next > period ? now + period : next + period;
    const scripted = script(now);
    const callbacks = pending; pending = [];
    for (const callback of callbacks) callback(now);
    quest.frames++;
    const sent = window.edgepose && window.edgepose.lastSent;
    if (scripted && sent && sent.seq !== quest.lastSeq) { quest.lastSeq = sent.seq; scripted.seq = sent.seq; quest.log.push(scripted); }
  }
  setTimeout(vsync, Math.max(0, next - performance.now() - 0.5));
}
vsync();
"""


def child_pids(pid):
    """Every process below `pid` (Linux /proc; empty elsewhere)."""
    parents = {}
    for entry in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = entry.read_text().rsplit(")", 1)[1].split()
        except OSError:                        # gone while we looked
            continue
        parents.setdefault(int(fields[1]), []).append(int(entry.parent.name))
    found, todo = [], [pid]
    while todo:
        for child in parents.get(todo.pop(), []):
            found.append(child)
            todo.append(child)
    return found


def keep_to_own_core(board_pid):
    """The board's child processes (Playwright's driver, the browser) onto the last core, niced: the
    headset's CPU is not the board's. Does nothing on one core or without sched_setaffinity."""
    cores = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else []
    if len(cores) < 2:
        return
    for pid in child_pids(board_pid):
        try:
            os.sched_setaffinity(pid, {cores[-1]})
            os.setpriority(os.PRIO_PROCESS, pid, 10)
        except OSError:                        # gone, or not ours
            pass


class EmulatedQuest:
    def __init__(self, take=None, hz=72.0, viewport=(640, 400)):
        self.take, self.hz, self.viewport = take, hz, viewport
        self._playwright = self.browser = self.page = self.context = None
        self.console_errors = []

    @staticmethod
    def missing():
        """Why the emulator cannot run on this machine (None: it can)."""
        try:
            importlib.import_module("playwright.sync_api")
        except ImportError:
            return "needs Playwright for Python (pip install -e '.[test]')"
        if not (Path(CHROMIUM).exists() or shutil.which(CHROMIUM)):
            return f"needs Chromium at {CHROMIUM} (apt-get install chromium; EDGEPOSE_CHROMIUM moves it)"
        if not IWER.exists():
            return (f"needs iwer from npm at {IWER} (npm install --prefix {NPM_CACHE} iwer; "
                    f"EDGEPOSE_NPM_CACHE moves it)")
        return None

    def _take_json(self):
        if self.take is None:
            return json.dumps(None)
        s = self.take.signals
        r = lambda a: np.round(np.asarray(a, np.float64).ravel(), 7).tolist()
        return json.dumps({"fps": self.take.fps, "frames": int(s.frames), "head_pos": r(s.head_pos), "head_rot": r(s.head_rot),
                           "hand_pos": r(s.hand_pos), "hand_rot": r(s.hand_rot)})

    def open(self, url):
        """Load the board's page in a new browser (or a new context of this one: a second headset)."""
        from playwright.sync_api import sync_playwright
        if self.browser is None:
            self._playwright = sync_playwright().start()
            self.browser = self._playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS,
                                                            headless=True)
        self.context = self.browser.new_context(ignore_https_errors=True, bypass_csp=True, viewport=dict(
            width=self.viewport[0], height=self.viewport[1]))
        page = self.page = self.context.new_page()
        page.on("console", lambda m: self.console_errors.append(m.text) if m.type == "error" else None)
        page.on("pageerror", lambda e: self.console_errors.append(str(e)))
        files = {"iwer.module.js": (IWER.read_bytes(), "text/javascript"),
                 "quest.js": (DRIVER_JS.replace("__HZ__", repr(self.hz)).encode(), "text/javascript"),
                 "take.json": (self._take_json().encode(), "application/json")}

        def emulator(route):
            name = route.request.url.split(EMULATOR_PATH, 1)[1]
            body, kind = files[name]
            route.fulfill(status=200, body=body, content_type=kind)

        page.route(f"**{EMULATOR_PATH}*", emulator)
        # Loaded by an init script, not by rewriting the page: a document Playwright fulfils has no network
        # address, and Chromium's local-network-access checks would then refuse its socket to the board.
        page.add_init_script(f'import("{EMULATOR_PATH}quest.js");')
        page.goto(url)
        page.wait_for_function("window.__quest && window.__quest.take !== null && window.edgepose")
        return page

    def pair(self, code, timeout=10.0):
        """Type the pairing code into the page, as a person would, and wait until the board welcomes it."""
        self.page.wait_for_selector("#code", state="visible", timeout=timeout * 1000)
        self.page.fill("#code", code)
        self.page.click("#pair-button")

    def wait(self, expression, timeout=10.0):
        self.page.wait_for_function(expression, timeout=timeout * 1000)

    def play(self, origin_page_ms):
        """Start the take: its frame 0 at this page time (performance.now(), ms)."""
        self.page.evaluate(f"window.__quest.origin = {float(origin_page_ms)!r}")

    def enter(self, mode="immersive-vr"):
        self.page.click("#enter-vr" if mode == "immersive-vr" else "#enter-ar")
        self.wait("window.edgepose.session !== null")

    def state(self):
        return self.page.evaluate("JSON.parse(JSON.stringify(window.edgepose))")

    def log(self):
        """The scripted pose of every frame the page sent: [{seq, head_pos, head_rot, hand_pos, hand_rot}]."""
        return self.page.evaluate("window.__quest.log")

    def page_now_ms(self):
        return self.page.evaluate("performance.now()")

    def another(self):
        """A second headset in the same browser (its own context: its own storage, its own pairing)."""
        other = EmulatedQuest(self.take, self.hz, self.viewport)
        other._playwright, other.browser, other._shared = self._playwright, self.browser, True
        return other

    def close(self):
        if getattr(self, "_shared", False):
            if self.context is not None:
                self.context.close()
                self.context = None
        elif self.browser is not None:
            self.browser.close()
            self._playwright.stop()
        self.browser = None


class QuestHeadset:
    """The replay harness's live headset (edgetools.sim.replay's `headset=`): the board's webxr:// source on
    loopback, and an EmulatedQuest that pairs with it and plays the take from the session's time 0."""

    def __init__(self, take, state_dir, hz=72.0, screenshot=None):
        self.url = f"webxr://127.0.0.1:0?state={state_dir}"
        self.quest = EmulatedQuest(take, hz)
        self.source, self.screenshot = None, screenshot
        self.state = self.log = None

    def prepare(self, service, timeout=10.0):
        """Open the page, type the code, and wait until the board has the page's clock."""
        import time
        self.source = service.headset.source
        self.quest.open(self.source.page_urls()[0])
        keep_to_own_core(os.getpid())     # the replay's headset on its own core (not in the pairing test)
        self.quest.pair(self.source.code)
        self.quest.wait("window.edgepose.paired", timeout)
        give_up = time.monotonic() + timeout
        while self.source.clock_offset_ms is None and time.monotonic() < give_up:
            time.sleep(0.01)
        time.sleep(1.0)                   # more pings for the minimum-delay filter

    def start(self, clock):
        """The take's frame 0 at the session clock's 0 (clock.t0 on time.monotonic, the source's clock)."""
        self.quest.play(clock.t0 * 1000.0 - self.source.clock_offset_ms)
        self.quest.enter("immersive-vr")

    def finish(self):
        """The page's counters, the scripted poses it sent, and (with `screenshot`) a picture of its view."""
        self.state, self.log = self.quest.state(), self.quest.log()
        self.state["emulated_frames"] = self.quest.page.evaluate("window.__quest.frames")
        if self.screenshot:
            # Three pictures 0.15 s apart: on a loaded 2-core machine one can land between the page's
            # draws (a cleared canvas); a body that is drawn shows in at least one.
            import time
            shot = Path(self.screenshot)
            for k in range(3):
                self.quest.page.screenshot(path=str(shot if k == 0 else shot.with_name(f"{shot.stem}-{k}{shot.suffix}")))
                time.sleep(0.15)

    def close(self):
        self.quest.close()
