"""int8 builds of the exported ONNX models.

    python -m quantize                  # models/{decoder,autoencoder}.int8.onnx + their manifest entries
    python -m quantize.report --data ../shared/mocap --json out/quant_report.json   # fp32 vs int8

`quantize.build` makes and chooses the int8 models (dynamic per-channel QInt8 vs static QDQ calibrated on
`train`), `quantize.report` measures them against fp32, `quantize.common` holds what both use.
Needs the `onnx` package (onnxruntime.quantization imports it); the runtime itself does not.
"""
