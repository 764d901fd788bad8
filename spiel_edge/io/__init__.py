"""Recorded acquisitions in: spiel-csv folders (``spiel_csv``) and MCAP recordings (``mcap``);
writing MCAP is an output (``spiel_edge.outputs.mcap``)."""
