"""Measurement kinds as data: components, measurement models and kinds.

* :mod:`.components` — one frozen record per component of a measurement vector (name,
  unit, angle or not, wire std field, limits);
* :mod:`.models` — the :class:`~.models.MeasurementModel` protocol every filter's
  ``update`` takes, and its implementations;
* :mod:`.kinds` — one record per measurement kind (components, family, model factory,
  what one report can start a track from), the table everything else reads.

The package imports nothing at its top: import the module you need.
"""
