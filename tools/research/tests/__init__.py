"""Tests of the research helpers: ``python -m pytest tools/research``."""
