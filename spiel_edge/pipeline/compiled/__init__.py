"""The compiled path: the stages run as one numba call per acquisition (docs/pipeline.md)."""
