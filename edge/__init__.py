"""The board runtime: from synchronised tracker signals to a full-body pose every frame (numpy, onnxruntime, and a C core)."""
