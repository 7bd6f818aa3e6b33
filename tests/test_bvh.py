"""BVH loading on all three source skeletons, and clear errors on malformed files."""
import numpy as np
import pytest

from motion import bvh
from motion.bvh import BvhError
from tests.conftest import SKELETON_CLIPS

TINY = """HIERARCHY
ROOT Hips
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation
  JOINT Leg
  {
    OFFSET 0 -10 0
    CHANNELS 3 Zrotation Yrotation Xrotation
    End Site
    {
      OFFSET 0 -10 0
    }
  }
}
MOTION
Frames: 2
Frame Time: 0.0333333
0 100 0 0 0 0 0 0 0
0 100 0 0 0 0 90 0 0
"""


def test_tiny_file_loads_with_end_site_and_fk():
    clip = bvh.parse(TINY)
    assert clip.names == ["Hips", "Leg", "Leg_end"]
    assert clip.frames == 2 and abs(clip.fps - 30) < 1e-3
    _, pos = clip.world()
    assert np.allclose(pos[0, 2], [0, 80, 0])
    # Leg rotated 90 deg about Z swings its child from -Y to +X.
    assert np.allclose(pos[1, 2], [10, 90, 0], atol=1e-9)


@pytest.mark.parametrize("source", sorted(SKELETON_CLIPS))
def test_loads_every_source_skeleton(mocap, source):
    clip = bvh.load(mocap / SKELETON_CLIPS[source])
    assert clip.frames > 30
    assert min(abs(clip.fps - 30), abs(clip.fps - 60)) < 0.01
    _, pos = clip.world()
    assert np.all(np.isfinite(pos))
    height = pos[:, :, 1].max(1) - pos[:, :, 1].min(1)
    assert 100 < np.median(height) < 220  # a person, in centimetres


@pytest.mark.parametrize("text, message", [
    (TINY[: TINY.index("MOTION")], "no MOTION section"),
    (TINY.rsplit("\n", 2)[0] + "\n", "only 1 are present"),
    (TINY.replace("0 100 0 0 0 0 90 0 0", "0 100 0 0 0 0 90 0"), "has 8 values"),
    (TINY.replace("CHANNELS 3 Zrotation", "CHANNELS 4 Zrotation"), "CHANNELS says 4 but lists 3"),
    (TINY.replace("0 100 0 0 0 0 90 0 0", "0 100 0 0 nan 0 90 0 0"), "not a finite number"),
    (TINY.replace("Frames: 2", "Frames: two"), "not numbers"),
    ("", "does not start with HIERARCHY"),
    (TINY.replace("Xrotation\n  JOINT", "Wrotation\n  JOINT"), "unknown channel"),
])
def test_malformed_file_gives_a_clear_error(text, message):
    with pytest.raises(BvhError, match=message):
        bvh.parse(text, "bad.bvh")


def test_unreadable_file_is_a_bvh_error(tmp_path):
    p = tmp_path / "binary.bvh"
    p.write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(BvhError, match="binary.bvh"):
        bvh.load(p)
