"""The layers of docs/architecture.md hold: the board runtime (edge) imports neither the bridge nor the
tools, the bridge (firmware_bridge) imports no tool, and the runtime needs no third-party package but
numpy and onnxruntime. The contracts are in pyproject.toml ([tool.importlinter]); this runs them."""
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_imports_follow_the_layers():
    exe = shutil.which("lint-imports", path=str(Path(sys.executable).parent))
    if exe is None:
        pytest.skip("import-linter is not installed (it is in the test extra: pip install -e '.[test]')")
    run = subprocess.run([exe, "--no-cache"], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-2000:]
    assert "0 broken" in run.stdout
