"""The suite on a bare install: ./scripts/test without EDGEPOSE_EXTRAS installs none of the optional
extras (torch, onnx, matplotlib, pillow), which CI's run has. Run with those made unimportable
(--without-extras, tests/conftest.py), the whole suite still collects, and the tests that reach for an
extra skip and say why instead of failing."""
import subprocess
import sys

from tests.conftest import ROOT

# The test files that use an extra or the packages built on one (models, quantize, viz), fast here
# because what needs the extra skips; the rest of the suite is collected below.
USES_EXTRAS = ["tests/test_models.py", "tests/test_quantize.py", "tests/test_int8check.py", "tests/test_batches.py",
               "tests/test_train_device.py", "tests/test_train_ddp.py", "tests/test_report.py",
               "tests/test_docs.py::test_every_dotted_name_the_docs_cite_exists"]


def pytest_bare(*args):
    return subprocess.run([sys.executable, "-m", "pytest", "--without-extras", "-q", "-p", "no:cacheprovider", *args],
                          cwd=ROOT, capture_output=True, text=True, timeout=300)


def test_without_the_extras_the_suite_collects_and_what_needs_them_skips_saying_why():
    collected = pytest_bare("--collect-only", "tests")
    assert collected.returncode == 0, collected.stdout[-3000:] + collected.stderr[-2000:]
    run = pytest_bare("-rs", *USES_EXTRAS)
    assert run.returncode == 0, run.stdout[-4000:] + run.stderr[-2000:]
    assert "needs torch (pip install -e '.[train]')" in run.stdout          # skipped, saying what to install
    assert " passed" in run.stdout.splitlines()[-1]
