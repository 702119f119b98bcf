"""What a Cursor-on-Target event is called and how long it stays valid, as data: the
MIL-STD-2525 types of a track, an emitter fix and a sensor (by kind, in :mod:`.cot`) and
the default stale time, so that the command line offers them as defaults without
loading the exporter."""

TYPE_TRACK = "a-u-A"
TYPE_EMITTER = "a-u-G-E"
TYPE_SENSOR = "a-f-G-E-S"
STALE_S = 60.0
