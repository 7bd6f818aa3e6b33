"""The code base passes ruff with the rules pyproject.toml selects ([tool.ruff.lint]: pyflakes, bugbear,
syntax errors). Run here so `./scripts/test`, and with it .ci/run, runs the linter; `ruff check .` in
the checkout says the same, with `--fix` for the findings it can mend itself."""
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def ruff():
    exe = shutil.which("ruff", path=str(Path(sys.executable).parent))
    if exe is None:
        pytest.skip("ruff is not installed (it is in the test extra: pip install -e '.[test]')")
    return exe


def test_the_code_base_passes_ruff():
    run = subprocess.run([ruff(), "check", "--no-cache", "--output-format", "concise", "."], cwd=ROOT,
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, "ruff check found:\n" + run.stdout[-6000:] + run.stderr[-2000:]


def test_ruff_reads_the_rules_from_pyproject(tmp_path):
    """A name used before a later import in the same function (F823, edge eval --report's old crash) and a
    zip() without strict= (B905) are reported with the project's settings, so the check above is live."""
    bad = tmp_path / "bad.py"
    bad.write_text("from pathlib import Path\n\n\ndef f(a, b):\n    p = Path('x')\n    from pathlib import Path\n"
                   "    return p, Path, list(zip(a, b))\n")
    run = subprocess.run([ruff(), "check", "--no-cache", "--output-format", "concise", "--config",
                          str(ROOT / "pyproject.toml"), str(bad)], capture_output=True, text=True, timeout=60)
    assert run.returncode == 1 and "F823" in run.stdout and "B905" in run.stdout, run.stdout + run.stderr
