"""int8 builds of the exported ONNX models (see the quantization issue)."""
