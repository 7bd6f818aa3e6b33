"""The int8 self-check at start-up (edge.int8check): the shipped int8 agrees with fp32 on this CPU; int8
that does not is replaced by fp32 and said so once, on stderr, the status line and in the summaries;
and on an emulated x86 CPU without VNNI (QEMU's Haswell model, where ORT's u8 x s8 kernel saturates
8-bit weights) the shipped 7-bit weights give the very figures they give here."""
import io
import json
import shutil
import subprocess
import sys

import numpy as np
import pytest

from edge.int8check import BOUNDS, REFERENCE
from edge.modelfiles import DEFAULT_DIR
from edge.options import PipelineOptions
from edge.pipeline import Pipeline
from motion.takes import from_sample
from tests.conftest import ROOT, SAMPLE


def test_the_shipped_int8_passes_its_self_check_on_this_cpu():
    pipe = Pipeline(PipelineOptions(samples=1, precision="int8"))
    check = pipe.manifest["int8_check"]
    assert pipe.precision == "int8" and pipe.precision_note == ""
    assert check["ok"] and check["decoder_fk_max_cm"] <= BOUNDS["decoder_fk_max_cm"]
    assert check["autoencoder_score_mean_cm"] <= BOUNDS["autoencoder_score_mean_cm"] and check["verdicts_same"] == 1.0
    assert check["decoder_fk_max_cm"] > 0          # it compared two different models, not one with itself


@pytest.fixture
def strict_models(tmp_path):
    """The shipped models with the self-check's decoder bound at 0.01 mm: as if this CPU's int8 disagreed."""
    folder = tmp_path / "models"
    shutil.copytree(DEFAULT_DIR, folder, ignore=shutil.ignore_patterns("*.py", "checkpoints", "__pycache__"))
    manifest = json.loads((folder / "manifest.json").read_text())
    manifest["files"][REFERENCE]["bounds"] = {"decoder_fk_max_cm": 0.001}
    (folder / "manifest.json").write_text(json.dumps(manifest, indent=2))
    return folder


def test_int8_that_disagrees_falls_back_to_fp32_says_why_once_and_runs_fp32s_body(strict_models, capsys):
    pipe = Pipeline(PipelineOptions(samples=1, precision="int8"), models=strict_models)
    again = Pipeline(PipelineOptions(samples=1, precision="int8"), models=strict_models)
    said = capsys.readouterr().err
    assert pipe.precision == "fp32" and not pipe.manifest["int8_check"]["ok"]
    assert pipe.precision_note.startswith("int8 off on this CPU: decoder FK ") and "bound 0.001" in pipe.precision_note
    assert said.count("int8 off on this CPU") == 1 and "running the fp32 models" in said     # once a process
    assert again.precision == "fp32"
    take = from_sample(SAMPLE)
    fp32 = Pipeline(PipelineOptions(samples=1, precision="fp32"), models=strict_models)
    for t in range(30):
        got, want = pipe.step(take.signals.slice(t, t + 1)), fp32.step(take.signals.slice(t, t + 1))
    assert np.array_equal(got.positions, want.positions)


def test_the_service_status_line_and_summary_say_int8_is_off(strict_models):
    from firmware_bridge import config
    from firmware_bridge.service import Service
    cfg = config.from_dict({"headset": {"url": "serial:///dev/ttyNOPE?role=headset"}, "output": {"pose_stream": "headset"},
                            "runtime": {"models": str(strict_models), "precision": "int8", "samples": 1}}, "test")
    status = io.StringIO()
    svc = Service(cfg, status=status, threaded=False)
    assert "edge run: precision fp32 (int8 off on this CPU: decoder FK" in status.getvalue()
    svc.show_status(final=True)
    assert "| precision fp32 (int8 off on this CPU: decoder FK" in status.getvalue().splitlines()[-1]
    s = svc.summary()
    assert s["precision"] == "fp32" and s["int8_check"]["ok"] is False and s["precision_note"]
    svc.close()


QEMU = shutil.which("qemu-x86_64-static") or shutil.which("qemu-x86_64")
EMULATED = """
import json, sys
from pathlib import Path
from edge.inference import make_session
from edge.int8check import compare, read_reference
folder = Path(sys.argv[1]); m = json.loads((folder / "manifest.json").read_text())
s = lambda suffix: {k: make_session(folder / f"{k}{suffix}.onnx") for k in ("decoder", "autoencoder")}
print(json.dumps(compare(s(".int8"), s(""), read_reference(folder / "int8_check.npz"), m["plausibility_threshold_m"]).as_dict()))
"""


@pytest.mark.skipif(QEMU is None or sys.platform != "linux", reason="needs qemu-x86_64-static (apt-get install qemu-user-static)")
def test_on_an_emulated_avx2_cpu_the_7_bit_weights_agree_and_8_bit_ones_saturate(tmp_path):
    pytest.importorskip("onnx", reason="quantizing needs the onnx package")
    import quantize.build as qb
    full = tmp_path / "full"
    shutil.copytree(DEFAULT_DIR, full, ignore=shutil.ignore_patterns("*.py", "checkpoints", "__pycache__"))
    old, qb.REDUCE_RANGE = qb.REDUCE_RANGE, False
    try:
        for model in ("decoder", "autoencoder"):
            qb.quantize_dynamic_model(full / f"{model}.onnx", full / f"{model}.int8.onnx")
    finally:
        qb.REDUCE_RANGE = old

    def check(folder, cpu=None):
        cmd = ([QEMU, "-cpu", cpu] if cpu else []) + [sys.executable, "-c", EMULATED, str(folder)]
        out = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300, check=True).stdout
        return json.loads(out.strip().splitlines()[-1])

    native, haswell = check(DEFAULT_DIR), check(DEFAULT_DIR, "Haswell")
    assert haswell == native and haswell["ok"]          # the same integers on both: the same figures
    saturated = check(full, "Haswell")
    assert not saturated["ok"] and saturated["autoencoder_score_mean_cm"] > 3 * haswell["autoencoder_score_mean_cm"]
