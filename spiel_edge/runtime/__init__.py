"""Running the pipeline over a source: the live loop over a board (``loop``), recordings
(``replay``), the empty-scene capture (``background``) and kernel warm-up (``warmup``)."""
