"""Many-target tracking: one tracker over injected parts (docs/algorithms.md, "Many targets").

:mod:`.table` (each track's life, its id, the priority order, duplicates),
:mod:`.hypotheses` (gated costs of plots against tracks), :mod:`.associators` (who took
which plot).
"""
