"""The board's stored config: a validated schema and its blob codec (``schema``, pure),
and flashing it over a device session (``flash``: pull, push, commit)."""
