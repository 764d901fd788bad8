"""Importing ``spiel_edge`` changes nothing process-wide (issue 42 item 8): the CPU numba
compiles for (``NUMBA_CPU_NAME``, a release wheel's prebuilt kernels need ``generic``) is
chosen by ``spiel_edge._jit``, the first of the package to import numba, just before it does."""

from __future__ import annotations

import os
import subprocess
import sys

from tests.house.imports import ROOT

PROBE = (
    "import os, sys\n"
    "import spiel_edge, spiel_edge.errors, spiel_edge.cli\n"
    "print(os.environ.get('NUMBA_CPU_NAME'), 'numba' in sys.modules)\n"
    "import spiel_edge._jit\n"
    "from numba.core import config\n"
    "print(os.environ.get('NUMBA_CPU_NAME'), config.CPU_NAME)\n"
)


def test_importing_the_package_sets_no_numba_cpu_the_jit_layer_does(tmp_path):
    env = {k: v for k, v in os.environ.items() if not k.startswith(("NUMBA_", "SPIEL_EDGE_"))}
    env["SPIEL_EDGE_KERNELS_OUT"] = str(tmp_path)  # a release build: the generic CPU is chosen
    out = subprocess.run(
        [sys.executable, "-c", PROBE], cwd=ROOT, env=env, capture_output=True, text=True, check=True
    )
    assert out.stdout.split("\n")[:2] == ["None False", "generic generic"]
