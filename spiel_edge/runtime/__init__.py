"""Running the pipeline over a source: the live loop over a board (``loop``), recordings
(``replay``), the empty-scene capture (``background``), kernel warm-up (``warmup``), the
kernels of a command prepared before it starts (``first_start``) and the display of what
compiles (``compile_progress``)."""
