"""The golden replay: a fixed 900-frame session through the board service, at N=1 and at N=8 with SSI,
in fp32, at the board's default look-ahead (none: each tick sends its own frame), gives the pose stream byte for byte as recorded (tests/golden/). A restructuring must not
change one byte; a change that means to (a new model, a new wire field) records them again:

    .venv/bin/python tests/test_golden.py --record

The recording pins the model files and the session it was made from, so a test that fails says
whether the code or its inputs changed.
"""
import gzip
import hashlib
import io
import json
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
GOLDEN = Path(__file__).parent / "golden"
SESSION = ROOT / "samples" / "cmu_09_12_walk.session.npz"
SECONDS = 15.0                  # 900 model ticks at 60 Hz
SAMPLES = (1, 8)
LOOKAHEAD = 0                   # the board's default ([runtime] lookahead)
PINNED = [SESSION, ROOT / "models" / "decoder.onnx", ROOT / "models" / "autoencoder.onnx",
          ROOT / "models" / "manifest.json"]


def sha256(path):
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def pose_stream(samples):
    """The bytes the host reads from the board's headset link over the golden session."""
    from edgetools.sim.replay import replay
    from edgetools.sim.session import Session
    log = io.BytesIO()
    result = replay(Session.load(str(SESSION)), "max", seconds=SECONDS, pose_log=log, runtime={"samples": samples, "lookahead": LOOKAHEAD, "precision": "fp32"})
    assert result["errors"] == [], result["errors"]
    return log.getvalue(), result


def frames(stream):
    from firmware_bridge.wire import messages
    return messages.FrameReader(accept=(messages.POSE_FRAME,)).feed(stream)


def first_difference(got, want):
    """Where two pose streams part: the frame and its fields that differ."""
    a, b = frames(got), frames(want)
    for i, (x, y) in enumerate(zip(a, b, strict=False)):
        fields = [k for k in ("t", "root_pos", "rotations", "contacts", "num_samples", "ssi_flags", "trackers_lost")
                  if not np.array_equal(np.asarray(getattr(x, k)), np.asarray(getattr(y, k)))]
        if fields:
            return f"frame {i} (t={y.t:.4f} s) differs in {', '.join(fields)}"
    return f"{len(a)} frames decoded, {len(b)} recorded"


@pytest.mark.parametrize("samples", SAMPLES)
def test_pose_stream_is_byte_identical_to_the_recording(samples):
    meta = json.loads((GOLDEN / "meta.json").read_text())
    changed = [p.name for p in PINNED if meta["sha256"][p.name] != sha256(p)]
    assert not changed, (f"the golden recording was made with other {', '.join(changed)}; if that change is meant, "
                         f"record again: .venv/bin/python tests/test_golden.py --record")
    want = gzip.decompress((GOLDEN / f"demo_n{samples}_fp32.bin.gz").read_bytes())
    got, result = pose_stream(samples)
    assert result["frames_out"] == meta["frames_out"][str(samples)]
    assert got == want, first_difference(got, want)


def record():
    GOLDEN.mkdir(exist_ok=True)
    meta = {"session": SESSION.name, "seconds": SECONDS, "precision": "fp32", "lookahead": LOOKAHEAD,
            "sha256": {p.name: sha256(p) for p in PINNED}, "frames_out": {}, "ssi_switches": {}}
    for n in SAMPLES:
        stream, result = pose_stream(n)
        (GOLDEN / f"demo_n{n}_fp32.bin.gz").write_bytes(gzip.compress(stream, 9, mtime=0))
        meta["frames_out"][str(n)], meta["ssi_switches"][str(n)] = result["frames_out"], result["ssi_switches"]
        print(f"N={n}: {len(stream)} bytes, {result['frames_out']} frames, {result['ssi_switches']} SSI switches")
    (GOLDEN / "meta.json").write_text(json.dumps(meta, indent=2) + "\n")


if __name__ == "__main__":
    if sys.argv[1:] != ["--record"]:
        sys.exit(__doc__)
    sys.path.insert(0, str(ROOT))
    record()
