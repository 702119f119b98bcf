"""The fused picture out of zfusion: a GeoJSON file for GIS tools and Cursor-on-Target
events for TAK. Each exporter is a sans-I/O core (a fused estimate in, a document or an
event out: :mod:`.geojson`, :mod:`.cot`) behind one process loop (:mod:`.process`) that
joins Zenoh like the recorder and keeps the current picture (:mod:`.tracks`)."""
