"""The topologies a method runs in: where its estimation runs and what flows between
the local nodes beside the sensors and the centre.

``centralised``: the sensors' measurements go to the centre, which runs the method.
``distributed``: a local tracker per sensor sends its track up; the centre fuses them.
``feedback``: as ``distributed``, and the fused track is fed back as every local
tracker's next prior. ``two-stage``: the local trackers only predict (from the fed-back
fused track) and send the prediction with their measurement up; the centre fuses the
predictions, updates that with each measurement, and fuses those updates.

A leaf module (no imports), so a scenario loader can check a topology's name without
loading the estimation methods; each method's topology is its registry record's
(:mod:`fusion.methods`).
"""

TOPOLOGIES = ("centralised", "distributed", "feedback", "two-stage")
