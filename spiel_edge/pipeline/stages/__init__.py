"""The pipeline's stages, one module each, in data-flow order (docs/pipeline.md, "Stages")."""
