"""The learned models in numba, each checked against onnxruntime (docs/pipeline.md)."""
