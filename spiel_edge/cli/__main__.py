"""``python -m spiel_edge.cli``: the same as the ``spiel-edge`` command."""

import sys

from spiel_edge.cli import main

sys.exit(main())
