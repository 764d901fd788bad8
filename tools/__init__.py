"""Workstation tools, by purpose: ``train`` (models, fitted parameters, data), ``bench``
(benchmarks and evidence), ``release`` (checks before a release), ``research`` (studies and
prototypes, not the product). Run from the checkout as ``python -m tools.PURPOSE.NAME``;
nothing here is installed or imported at run time."""
