"""firmware_bridge/wire/protocol.md lists the rest-pose bone offsets a POSE_FRAME receiver needs; they
are edge.skeleton's, to the millimetre."""
import re
from pathlib import Path

import numpy as np

from edge.skeleton import JOINT_NAMES, OFFSETS, PARENTS

DOC = Path(__file__).resolve().parents[1] / "firmware_bridge" / "wire" / "protocol.md"


def test_the_documented_joint_table_is_the_skeleton():
    rows = re.findall(r"^\| (\d+) \| (\w+) \| (-|\d+) \| \d+\.\.\d+ \| ([-\d.]+) \| ([-\d.]+) \| ([-\d.]+) \|$",
                      DOC.read_text(), flags=re.M)
    assert len(rows) == len(JOINT_NAMES)
    for j, name, parent, x, y, z in rows:
        j = int(j)
        assert name == JOINT_NAMES[j] and (int(parent) if parent != "-" else -1) == PARENTS[j]
        assert np.allclose([float(x), float(y), float(z)], OFFSETS[j], atol=5e-4)
