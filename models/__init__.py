"""Training side (the [train] extra; torch lives only here): the networks (`nets`), the training
windows made on the accelerator (`batches`), training (`train`), ONNX export (`export`), and the
shipped ONNX models, manifest, checkpoints and model card as package data."""
