"""Training side: data pipeline, networks, training and ONNX export. Torch lives only here."""
