"""The commands' file rules: which files may be read and written and how (``guard``), and how
large an input may be before it is parsed (``limits``). Recordings are in
:mod:`spiel_edge.recordings`."""
