import os
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


@pytest.fixture(scope="session")
def mocap():
    if not (MOCAP / "MANIFEST.tsv").exists():
        pytest.skip(f"needs the training data at {MOCAP} (../shared/mocap; set EDGEPOSE_MOCAP to move it)")
    return MOCAP


@pytest.fixture(scope="session")
def torch():
    return pytest.importorskip("torch", reason="needs torch (pip install -e '.[train]')")
