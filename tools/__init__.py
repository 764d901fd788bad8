"""Workstation tools: training, evidence, benchmark helpers. Run from the checkout as
``python -m tools.NAME``; nothing here is installed or imported at run time."""
