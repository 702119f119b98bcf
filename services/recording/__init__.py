"""The recorder: everything on a deployment's keys into one Rerun recording.

- :mod:`.recorder` — the process and its :class:`~.recorder.Recorder`: decoding,
  validation, what is drawn where, scoring against truth;
- :mod:`.stream` — the Rerun stream that queues rows and sends them as columns, the
  blueprint, opening a file (and a viewer);
- :mod:`.draw` — geometry and styling, pure numpy (ellipsoids, rays, colours, paths);
- :mod:`.map` — the same picture in lat/lon for the map view.

Nothing is imported here, so that reading :mod:`.draw` (as the scoring does) does not
load the Rerun SDK.
"""
