"""A small, strict BVH reader.

Returns the hierarchy (joint names, parents, offsets, channels, end sites as extra leaf joints)
and the motion as per-joint local rotations (quaternions) and root translations, in the file's units.
Malformed files raise BvhError with the line that is wrong, never a bare traceback.
"""
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from edge import quat


class BvhError(ValueError):
    """A BVH file that cannot be read: the message names the file, the line and what is wrong."""


@dataclass
class BvhClip:
    path: str
    names: list            # joint names; end sites are named '<parent>_end'
    parents: np.ndarray    # [J], -1 for the root
    offsets: np.ndarray    # [J,3] in file units
    fps: float
    rotations: np.ndarray  # [T,J,4] local quaternions (identity for end sites)
    positions: np.ndarray  # [T,J,3] local translations (offsets, or position channels where present)

    @property
    def frames(self):
        return self.rotations.shape[0]

    def index(self, name):
        try:
            return self.names.index(name)
        except ValueError:
            raise BvhError(f"{self.path}: no joint named {name!r}") from None

    def world(self):
        """Forward kinematics: (world rotations [T,J,4], world positions [T,J,3])."""
        T, J = self.rotations.shape[:2]
        wr = np.empty_like(self.rotations)
        wp = np.empty_like(self.positions)
        for j in range(J):
            p = self.parents[j]
            if p < 0:
                wr[:, j] = self.rotations[:, j]
                wp[:, j] = self.positions[:, j]
            else:
                wr[:, j] = quat.mul(wr[:, p], self.rotations[:, j])
                wp[:, j] = wp[:, p] + quat.rotate(wr[:, p], self.positions[:, j])
        return wr, wp


_ROT = {"Xrotation": "X", "Yrotation": "Y", "Zrotation": "Z"}
_POS = {"Xposition": 0, "Yposition": 1, "Zposition": 2}


def load(path):
    path = str(path)
    try:
        text = Path(path).read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise BvhError(f"{path}: cannot read file ({e})") from None
    return parse(text, path)


def parse(text, path="<bvh>"):
    """A BVH file's text -> BvhClip; anything malformed raises BvhError naming the file and line."""
    src = _Lines(text.splitlines(), path)
    names, parents, offsets, channels = _hierarchy(src)
    n_frames, frame_time = _motion_header(src)
    data = _frames(src, n_frames, sum(len(c) for c in channels))
    rotations, positions = _pose_channels(data, np.array(offsets, dtype=np.float64), channels)
    return BvhClip(path, names, np.array(parents), np.array(offsets, dtype=np.float64), 1.0 / frame_time,
                   rotations, positions)


class _Lines:
    """The file's lines and the reader's place in them; fail() raises BvhError at a line."""

    def __init__(self, lines, path):
        self.lines, self.path, self.i = lines, path, 0

    def fail(self, msg, line=None):
        where = f" line {line + 1}" if line is not None else ""
        raise BvhError(f"{self.path}:{where}: {msg}")

    def skip_blank(self):
        while self.i < len(self.lines) and not self.lines[self.i].strip():
            self.i += 1

    def here(self):
        """The current line's index, or None past the end (for fail)."""
        return self.i if self.i < len(self.lines) else None


def _hierarchy(src):
    """HIERARCHY ... MOTION -> joint names, parents, offsets, channels (in file order)."""
    names, parents, offsets, channels, stack = [], [], [], [], []
    fail, lines = src.fail, src.lines
    src.skip_blank()
    if src.here() is None or lines[src.i].strip() != "HIERARCHY":
        fail("file does not start with HIERARCHY", src.here())
    src.i += 1
    pending = None  # joint declared, waiting for '{'
    while src.i < len(lines):
        tok, at = lines[src.i].split(), src.i
        src.i += 1
        if not tok:
            continue
        key = tok[0]
        if key in ("ROOT", "JOINT"):
            if len(tok) < 2:
                fail(f"{key} without a name", at)
            if key == "ROOT" and stack:
                fail("ROOT inside another joint", at)
            pending = (" ".join(tok[1:]), stack[-1] if stack else -1)
        elif key == "End":
            if not stack:
                fail("End Site outside a joint", at)
            pending = (names[stack[-1]] + "_end", stack[-1])
        elif key == "{":
            if pending is None:
                fail("'{' without a joint", at)
            names.append(pending[0])
            parents.append(pending[1])
            offsets.append(None)
            channels.append([])
            stack.append(len(names) - 1)
            pending = None
        elif key == "}":
            if not stack:
                fail("unbalanced '}'", at)
            j = stack.pop()
            if offsets[j] is None:
                fail(f"joint {names[j]!r} has no OFFSET", at)
        elif key == "OFFSET":
            offsets[_inside(stack, src, at)] = _offset(tok, src, at)
        elif key == "CHANNELS":
            channels[_inside(stack, src, at, "CHANNELS outside a joint")] = _channels(tok, src, at)
        elif key == "MOTION":
            break
        else:
            fail(f"unexpected {key!r} in HIERARCHY", at)
    else:
        fail("no MOTION section (file truncated?)")
    if stack:
        fail(f"hierarchy not closed: joint {names[stack[-1]]!r} is missing its '}}'")
    if not names:
        fail("hierarchy has no joints")
    return names, parents, offsets, channels


def _inside(stack, src, at, msg="OFFSET needs three numbers inside a joint"):
    """The joint a line belongs to (the innermost open one)."""
    if not stack:
        src.fail(msg, at)
    return stack[-1]


def _offset(tok, src, at):
    if len(tok) != 4:
        src.fail("OFFSET needs three numbers inside a joint", at)
    try:
        return [float(v) for v in tok[1:]]
    except ValueError:
        src.fail(f"OFFSET values are not numbers: {' '.join(tok[1:])}", at)


def _channels(tok, src, at):
    if len(tok) < 2:
        src.fail("CHANNELS outside a joint", at)
    try:
        n = int(tok[1])
    except ValueError:
        src.fail(f"CHANNELS count is not a number: {tok[1]}", at)
    ch = tok[2:]
    if n != len(ch):
        src.fail(f"CHANNELS says {n} but lists {len(ch)}", at)
    bad = [c for c in ch if c not in _ROT and c not in _POS]
    if bad:
        src.fail(f"unknown channel {bad[0]!r}", at)
    return ch


def _motion_header(src):
    """Frames: and Frame Time: after MOTION -> (frames, seconds a frame), both positive."""
    def header(prefix):
        src.skip_blank()
        if src.here() is None or not src.lines[src.i].strip().startswith(prefix):
            src.fail(f"expected '{prefix}' after MOTION", src.here())
        value = src.lines[src.i].split(":", 1)[1].strip()
        src.i += 1
        return value

    try:
        n_frames = int(header("Frames"))
        frame_time = float(header("Frame Time"))
    except ValueError:
        src.fail("Frames / Frame Time are not numbers", src.i - 1)
    if n_frames <= 0 or not (frame_time > 0):
        src.fail(f"Frames ({n_frames}) and Frame Time ({frame_time}) must be positive", src.i - 1)
    return n_frames, frame_time


def _frames(src, n_frames, n_ch):
    """The motion rows -> [frames, channels] float64, every value finite."""
    fail = src.fail
    body = [ln for ln in src.lines[src.i:] if ln.strip()]
    if len(body) < n_frames:
        fail(f"header says {n_frames} frames but only {len(body)} are present (file truncated?)")
    try:
        data = np.array([ln.split() for ln in body[:n_frames]], dtype=np.float64)
    except ValueError:
        counts = {len(ln.split()) for ln in body[:n_frames]}
        if len(counts) > 1 or counts != {n_ch}:
            bad = next(k for k, ln in enumerate(body[:n_frames]) if len(ln.split()) != n_ch)
            fail(f"frame {bad} has {len(body[bad].split())} values, the hierarchy declares {n_ch} channels")
        fail("motion data contains values that are not numbers")
    if data.ndim != 2 or data.shape[1] != n_ch:
        fail(f"motion rows have {data.shape[-1] if data.ndim == 2 else '?'} values, the hierarchy declares {n_ch} channels")
    if not np.all(np.isfinite(data)):
        r, c = np.argwhere(~np.isfinite(data))[0]
        fail(f"frame {r} channel {c} is not a finite number ({data[r, c]})")
    return data


def _pose_channels(data, offsets, channels):
    """The channels' values -> local rotations [T,J,4] (quaternions) and positions [T,J,3] (the offsets
    where a joint has no position channel)."""
    n_frames, J = len(data), len(channels)
    rotations = np.zeros((n_frames, J, 4))
    rotations[..., 0] = 1.0
    positions = np.broadcast_to(offsets, (n_frames, J, 3)).copy()
    col = 0
    for j, ch in enumerate(channels):
        rot_order = "".join(_ROT[c] for c in ch if c in _ROT)
        rot_cols = [col + k for k, c in enumerate(ch) if c in _ROT]
        for k, c in enumerate(ch):
            if c in _POS:
                positions[:, j, _POS[c]] = data[:, col + k]
        if rot_order:
            rotations[:, j] = quat.from_euler(data[:, rot_cols], rot_order)
        col += len(ch)
    return rotations, positions
