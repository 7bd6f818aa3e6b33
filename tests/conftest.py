"""Shared fixtures: the repository paths, the mocap folder (../shared/mocap or $EDGEPOSE_MOCAP; tests that need it skip without it) and sample takes."""
import os
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
MOCAP = Path(os.environ.get("EDGEPOSE_MOCAP", ROOT.parent / "shared" / "mocap"))
SAMPLE = ROOT / "samples" / "cmu_09_12_walk.npz"

# One clip per source skeleton.
SKELETON_CLIPS = {
    "cmu": "cmu_amc2bvh/02/02_01.bvh",
    "daz": "cmu_daz_ateliercircle/05/05_01.bvh",
    "bandai": "bandai_namco_ccbync/dataset-1/dataset-1_walk_normal_001.bvh",
}


# The optional extras' packages ([train], [quantize], [viz]): --without-extras runs the suite as on a
# machine that installed none of them (./scripts/test without EDGEPOSE_EXTRAS), whatever this one has.
EXTRAS = ("torch", "onnx", "matplotlib", "PIL")


def pytest_addoption(parser):
    parser.addoption("--without-extras", action="store_true",
                     help="make the optional extras unimportable (" + ", ".join(EXTRAS) + "), as on a bare install")


def pytest_configure(config):
    if config.getoption("--without-extras"):
        for name in EXTRAS:
            sys.modules[name] = None          # `import torch` now raises ImportError, as where it is absent


@pytest.fixture(scope="session")
def mocap():
    if not (MOCAP / "MANIFEST.tsv").exists():
        pytest.skip(f"needs the training data at {MOCAP} (../shared/mocap; set EDGEPOSE_MOCAP to move it)")
    return MOCAP


@pytest.fixture(scope="session")
def torch():
    return pytest.importorskip("torch", reason="needs torch (pip install -e '.[train]')")


def worn_signals(take, names=None, seed=0, drops=True):
    """The take's signals with extra IMUs worn (default: all seven), IMU noise, and drop-outs that make
    their flags fade out and back in (edge.imus), so tests cross every IMU path."""
    import numpy as np
    from edge.imus import IMU_LOCATIONS, ImuNoise, dragposer_drops, mask
    from motion.synth import wear
    rng = np.random.default_rng(seed)
    worn = mask(IMU_LOCATIONS if names is None else names)
    alive = dragposer_drops(rng, take.frames, worn, p=0.02, frames=50) if drops else None
    return wear(take.signals, worn, take.fps, rng, ImuNoise(), alive)
