"""Gateways for real sensors: ``zfusion ingest krakensdr`` and ``zfusion ingest jsonl``.

Each is a process that turns a device's own output into ordinary measurement messages
and watermarks on ``meas/<id>``, so every topology, recording and output works
unchanged. The formats are parsed without I/O (:mod:`.krakensdr`, :mod:`.jsonl`), the
checks that protect the fuser are one core (:mod:`.gateway`), and :mod:`.process`
only moves bytes: HTTP polls and POSTs, stdin, UDP, TCP, Zenoh. See ``docs/ingest.md``.
"""
