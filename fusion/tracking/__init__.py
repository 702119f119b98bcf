"""Many-target tracking: one tracker over injected parts (docs/design.md, "The many-target
tracker"; the rules in docs/algorithms.md, "Many targets").

:mod:`.manager` (:class:`~.manager.MultiTargetTracker`, the frame loop, and the parts'
protocols), :mod:`.table` (each track's life, its id, the priority order, duplicates),
:mod:`.hypotheses` (one scan's gated costs of plots against tracks; sequential gating),
:mod:`.associators` (who took which plot: an assignment, or weights for a PDA update),
:mod:`.initiators` (new 3D tracks from the plots no track took), :mod:`.config` (the
``[tracker]`` keys). The centralised methods (:mod:`fusion.mtt`), the network centre
(:mod:`fusion.network`) and the emitter tracker (:mod:`fusion.df.multi`) configure it.
"""
