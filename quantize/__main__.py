"""python -m quantize [--models DIR] [--data ../shared/mocap] [--methods dynamic,static] [--json OUT]
python -m quantize --jacobian-only [--models DIR]

Builds models/decoder.int8.onnx and models/autoencoder.int8.onnx from the fp32 exports and adds them to
models/manifest.json (the fp32 entries and all metadata stay). Re-run it after every fp32 re-export:
python -m models.export rewrites the manifest with the fp32 files only, and the runtime then says the
int8 files are not listed. Needs the `onnx` package (onnxruntime.quantization imports it).

The refiner's batch graph (decoder_jacobian.onnx, when exported) is built too, in dynamic int8;
--jacobian-only builds only that one and leaves the decoder's and autoencoder's files as they are.
"""
import argparse
import json
import sys
from pathlib import Path

from edge.modelfiles import DEFAULT_DIR, ModelError


def main(argv=None):
    ap = argparse.ArgumentParser(prog="python -m quantize", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--models", default=str(DEFAULT_DIR), help="folder with decoder.onnx, autoencoder.onnx, manifest.json")
    ap.add_argument("--data", default=str(Path(__file__).resolve().parent.parent.parent / "shared" / "mocap"),
                    help="mocap folder for static calibration and for choosing the method (default ../shared/mocap)")
    ap.add_argument("--methods", default="dynamic,static", help="candidates to build and compare")
    ap.add_argument("--json", default="out/quant_build.json", help="write what was built and measured here")
    ap.add_argument("--jacobian-only", action="store_true", help="build only decoder_jacobian.int8.onnx")
    a = ap.parse_args(argv)
    try:
        import onnx  # noqa: F401
    except ImportError:
        print("quantize: needs the onnx package (pip install onnx); onnxruntime.quantization imports it", file=sys.stderr)
        return 2
    from quantize.build import build, build_jacobian_only
    methods = tuple(m.strip() for m in a.methods.split(",") if m.strip())
    bad = set(methods) - {"dynamic", "static"}
    if bad:
        ap.error(f"unknown method(s) {sorted(bad)}: choose from dynamic, static")
    try:
        report = build_jacobian_only(a.models) if a.jacobian_only else build(a.models, a.data, methods)
    except ModelError as e:
        print(f"quantize: {e}", file=sys.stderr)
        return 2
    if a.json:
        Path(a.json).parent.mkdir(parents=True, exist_ok=True)
        Path(a.json).write_text(json.dumps(report, indent=2) + "\n")
    for name, f in report["files"].items():
        print(f"wrote {Path(a.models) / name} ({f['bytes']:,} bytes, {f.get('method', 'reference input')}, sha256 {f['sha256'][:12]}...)")
    print(f"updated {Path(a.models) / 'manifest.json'}" + (f"; details in {a.json}" if a.json else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
