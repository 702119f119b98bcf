"""EUROCONTROL ASTERIX, sans I/O: datagram bytes ↔ typed records.

Categories (one module each, the items zfusion reads or writes typed, every other item
of the UAP stepped over by its layout): CAT048 monoradar target reports
(:class:`TargetReport`), CAT034 monoradar service messages (:class:`ServiceMessage`),
CAT021 ADS-B reports (:class:`AdsbReport`), CAT062 system tracks
(:class:`SystemTrack`), CAT065 SDPS status (:class:`SdpsStatus`). The framing —
data blocks, FSPEC, the six item layouts — is :mod:`.framing`; why this is our own
codec and not a library is ``docs/asterix.md``.

:func:`decode` turns a datagram into records, and what cannot be read into
:class:`Undecodable` entries with a stable ``cause`` (``truncated``, ``malformed``,
``unknown-category``, ``missing-item``): a broken record loses the rest of its data
block (nothing in a block says where the next record starts) but not the datagram's
other blocks; a broken block header loses the rest of the datagram. :func:`encode`
packs records into datagrams of data blocks.

Times are times of day (s since midnight UTC, wrapping at 86 400 s);
:func:`utc_of_tod` places one on the UTC time line next to a reference clock.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Iterable, Union

from . import cat021, cat034, cat048, cat062, cat065
from .cat021 import AdsbReport, Quality
from .cat034 import NORTH_MARKER, SECTOR_CROSSING, ServiceMessage
from .cat048 import TargetReport
from .cat062 import Accuracy, SystemTrack
from .cat065 import SdpsStatus
from .framing import MAX_BLOCK, AsterixError, Category, block, blocks
from .units import DAY

Record = Union[TargetReport, ServiceMessage, AdsbReport, SystemTrack, SdpsStatus]


@dataclass(frozen=True)
class Codec:
    """One category: its UAP, and its items ↔ typed record."""

    category: Category
    decode: Callable[[dict[str, bytes]], Record]
    encode: Callable[[Record], bytes]


CODECS: dict[int, Codec] = {m.CATEGORY.cat: Codec(m.CATEGORY, m.decode, m.encode)
                            for m in (cat048, cat034, cat021, cat062, cat065)}


@dataclass(frozen=True)
class Undecodable:
    """What could not be read: its category (None: the block header), a stable cause
    and a one-line detail."""

    cat: int | None
    cause: str
    detail: str


def decode(data: bytes, codecs: dict[int, Codec] = CODECS) -> list[Record | Undecodable]:
    """Every record of a datagram, in order; :class:`Undecodable` for what is not."""
    out: list = []
    try:
        for cat, body in blocks(data):
            codec = codecs.get(cat)
            if codec is None:
                out.append(Undecodable(cat, "unknown-category", f"CAT{cat:03d} is not read here"))
                continue
            split, typed = codec.category.split, codec.decode
            pos, end = 0, len(body)
            while pos < end:
                try:
                    items, pos = split(body, pos, end)
                except AsterixError as e:
                    out.append(Undecodable(cat, e.cause, f"CAT{cat:03d}: {e} (the rest of the block is lost)"))
                    break
                try:
                    out.append(typed(items))
                except ValueError as e:
                    out.append(Undecodable(cat, "missing-item", f"CAT{cat:03d}: {e}"))
    except AsterixError as e:
        out.append(Undecodable(None, e.cause, f"{e} (the rest of the datagram is lost)"))
    return out


def encode(records: Iterable[Record], max_octets: int = MAX_BLOCK, codecs: dict[int, Codec] = CODECS) -> list[bytes]:
    """Records -> datagrams of at most ``max_octets`` (a record that alone is larger
    gets a datagram of its own): consecutive records of one category share a block."""
    datagrams: list[bytes] = []
    current = bytearray()
    cat, recs, size = None, [], 0

    def close_block():
        nonlocal current
        if recs:
            b = block(cat, recs)
            if current and len(current) + len(b) > max_octets:
                datagrams.append(bytes(current))
                current = bytearray()
            current += b

    for r in records:
        raw = codecs[r.category].encode(r)
        if r.category != cat or 3 + size + len(raw) > min(max_octets, MAX_BLOCK):
            close_block()
            cat, recs, size = r.category, [], 0
        recs.append(raw)
        size += len(raw)
    close_block()
    if current:
        datagrams.append(bytes(current))
    return datagrams


def utc_of_tod(tod: float, near: float) -> float:
    """The UTC time (POSIX s) whose time of day is ``tod`` nearest to ``near`` (the
    receiver's clock): a report of 23:59:59.9 received at 00:00:00.2 is of yesterday,
    one of 00:00:00.1 received at 23:59:59.8 of tomorrow. Exact while the clock is
    within 12 h of the truth."""
    t = math.floor(near / DAY) * DAY + tod
    if t - near > DAY / 2:
        t -= DAY
    elif near - t >= DAY / 2:
        t += DAY
    return t


__all__ = [
    "CODECS", "NORTH_MARKER", "SECTOR_CROSSING", "Accuracy", "AdsbReport", "AsterixError", "Codec", "Quality",
    "Record", "SdpsStatus", "ServiceMessage", "SystemTrack", "TargetReport", "Undecodable", "decode", "encode",
    "utc_of_tod",
]
