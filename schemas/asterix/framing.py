"""ASTERIX framing, spec-driven: a category is its UAP, a data item is its layout.

Everything that cuts bytes into data blocks, records and data items lives here; what an
item *means* lives in the category modules (:mod:`.cat048`, ...). A data block is
``CAT`` (1 octet), ``LEN`` (2 octets, counting the whole block) and its records. A
record is its FSPEC — octets whose bits 8…2 flag the items of FRN ``7k+1 … 7k+7`` and
whose bit 1 (FX) says another FSPEC octet follows — then the flagged items in FRN order.
The specifications give every data item one of six layouts (:class:`Fixed`,
:class:`Extended`, :class:`Repetitive`, :class:`RepetitiveFX`, :class:`Compound`,
:class:`Explicit`); knowing the layout of *every* item of a UAP is what lets a decoder
step over the items it does not read. A :class:`Category` is a UAP as data: one
``(name, layout)`` per FRN, ``None`` for a spare FRN.

A record that runs past its block, an FSPEC that flags a spare or missing FRN, a last
extent with FX set, an explicit length of zero: :class:`AsterixError`, with a short
``cause`` (``truncated`` or ``malformed``) for counters. Nothing here allocates more
than the input's size, so hostile bytes cost at most their length.

Speed: the plan of a record (which items, which layouts) depends only on its FSPEC, and
a radar sends a handful of distinct FSPECs; plans are cached per category
(:data:`PLAN_CACHE` entries at most).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Iterator, Mapping, Union

from .units import DAY, TOD_LSB

PLAN_CACHE = 256  # distinct FSPECs remembered per category
MAX_BLOCK = 0xFFFF  # LEN is two octets


class AsterixError(ValueError):
    """Bytes that are not ASTERIX of the expected layout. ``cause`` is short and stable."""

    def __init__(self, cause: str, detail: str):
        super().__init__(detail)
        self.cause = cause


def _truncated(what: str, need: int, end: int) -> AsterixError:
    return AsterixError("truncated", f"{what} needs octet {need}, the record ends at {end}")


# ------------------------------------------------------------------ the six layouts


@dataclass(frozen=True)
class Fixed:
    """``size`` octets."""

    size: int

    def end(self, data: bytes, pos: int, end: int) -> int:
        stop = pos + self.size
        if stop > end:
            raise _truncated("a fixed item", stop, end)
        return stop


@dataclass(frozen=True)
class Extended:
    """A primary part of ``first`` octets, then extents of ``then`` octets, each part
    ending in an FX bit; at most ``parts`` parts (the specification's)."""

    first: int = 1
    then: int = 1
    parts: int = 8

    def end(self, data: bytes, pos: int, end: int) -> int:
        stop = pos + self.first
        for k in range(self.parts):
            if stop > end:
                raise _truncated("an extended item", stop, end)
            if not data[stop - 1] & 1:
                return stop
            stop += self.then
        raise AsterixError("malformed", f"an extended item with more than {self.parts} parts")

    def split(self, raw: bytes) -> list[bytes]:
        """The parts, FX bits included."""
        out, pos = [raw[:self.first]], self.first
        while pos < len(raw):
            out.append(raw[pos:pos + self.then])
            pos += self.then
        return out

    @staticmethod
    def join(parts: list[bytes]) -> bytes:
        """Parts (FX bits clear) -> the item, FX set on every part but the last; trailing
        all-zero extents are left out."""
        while len(parts) > 1 and not any(parts[-1]):
            parts = parts[:-1]
        out = bytearray()
        for k, p in enumerate(parts):
            b = bytearray(p)
            b[-1] = (b[-1] & 0xFE) | (k < len(parts) - 1)
            out += b
        return bytes(out)


@dataclass(frozen=True)
class Repetitive:
    """REP (1 octet), then REP elements of ``size`` octets."""

    size: int

    def end(self, data: bytes, pos: int, end: int) -> int:
        if pos >= end:
            raise _truncated("a repetitive item", pos + 1, end)
        stop = pos + 1 + data[pos] * self.size
        if stop > end:
            raise _truncated("a repetitive item", stop, end)
        return stop

    def split(self, raw: bytes) -> list[bytes]:
        return [raw[1 + k * self.size:1 + (k + 1) * self.size] for k in range(raw[0])]

    def join(self, elements: list[bytes]) -> bytes:
        if len(elements) > 255 or any(len(e) != self.size for e in elements):
            raise ValueError(f"a repetitive item holds at most 255 elements of {self.size} octets")
        return bytes([len(elements)]) + b"".join(elements)


@dataclass(frozen=True)
class RepetitiveFX:
    """Elements of ``size`` octets, each ending in an FX bit (set: another follows)."""

    size: int
    max_elements: int = 255

    def end(self, data: bytes, pos: int, end: int) -> int:
        stop = pos + self.size
        for _ in range(self.max_elements):
            if stop > end:
                raise _truncated("a repetitive item", stop, end)
            if not data[stop - 1] & 1:
                return stop
            stop += self.size
        raise AsterixError("malformed", f"a repetitive item with more than {self.max_elements} elements")


@dataclass(frozen=True)
class Explicit:
    """LEN (1 octet, counting itself), then LEN − 1 octets (RE and SP fields)."""

    def end(self, data: bytes, pos: int, end: int) -> int:
        if pos >= end:
            raise _truncated("an explicit item", pos + 1, end)
        if data[pos] == 0:
            raise AsterixError("malformed", "an explicit item of length 0")
        stop = pos + data[pos]
        if stop > end:
            raise _truncated("an explicit item", stop, end)
        return stop


Layout = Union[Fixed, Extended, Repetitive, RepetitiveFX, "Compound", Explicit]


@dataclass(frozen=True)
class Compound:
    """A primary subfield — presence bits 8…2 per octet, FX in bit 1, like an FSPEC —
    then the present subfields in order; ``subfields`` holds ``(name, layout)`` per
    position, ``None`` for a spare one."""

    subfields: tuple[tuple[str, "Layout"] | None, ...]
    index: Mapping[str, int] = field(init=False, repr=False, compare=False)

    def __post_init__(self):
        object.__setattr__(self, "index", {s[0]: k for k, s in enumerate(self.subfields) if s is not None})

    def end(self, data: bytes, pos: int, end: int) -> int:
        return self._walk(data, pos, end, None)

    def _walk(self, data: bytes, pos: int, end: int, out: dict | None) -> int:
        present, pos = read_fspec(data, pos, end, "a compound item's primary subfield")
        for k in present:
            sub = self.subfields[k] if k < len(self.subfields) else None
            if sub is None:
                raise AsterixError("malformed", f"a compound item flags its spare subfield {k + 1}")
            stop = sub[1].end(data, pos, end)
            if out is not None:
                out[sub[0]] = data[pos:stop]
            pos = stop
        return pos

    def split(self, raw: bytes) -> dict[str, bytes]:
        out: dict[str, bytes] = {}
        self._walk(raw, 0, len(raw), out)
        return out

    def join(self, values: Mapping[str, bytes]) -> bytes:
        """Subfields by name -> the item (None or absent: not present)."""
        present = sorted(self.index[name] for name, v in values.items() if v is not None)
        return write_fspec(present) + b"".join(values[self.subfields[k][0]] for k in present)


def read_fspec(data: bytes, pos: int, end: int, what: str = "the FSPEC") -> tuple[list[int], int]:
    """The 0-based positions flagged by an FSPEC (or a compound's primary subfield) at
    ``pos``, and the position after it."""
    present: list[int] = []
    base = 0
    while True:
        if pos >= end:
            raise _truncated(what, pos + 1, end)
        octet = data[pos]
        pos += 1
        for bit in range(7):
            if octet & (0x80 >> bit):
                present.append(base + bit)
        if not octet & 1:
            return present, pos
        base += 7


def write_fspec(present: list[int]) -> bytes:
    """The FSPEC flagging these 0-based positions (sorted), FX where more follows."""
    if not present:
        return b"\x00"
    n = present[-1] // 7 + 1
    out = bytearray(n)
    for k in present:
        out[k // 7] |= 0x80 >> (k % 7)
    for i in range(n - 1):
        out[i] |= 1
    return bytes(out)


# ------------------------------------------------------------------ categories


@dataclass(frozen=True)
class Category:
    """One edition of one category's UAP: ``uap[frn - 1]`` is ``(item name, layout)``
    or None (a spare FRN)."""

    cat: int
    edition: str
    uap: tuple[tuple[str, Layout] | None, ...]
    frn: Mapping[str, int] = field(init=False, repr=False, compare=False)
    _plans: dict = field(init=False, repr=False, compare=False, default_factory=dict)

    def __post_init__(self):
        object.__setattr__(self, "frn", {e[0]: k for k, e in enumerate(self.uap) if e is not None})

    def _plan(self, fspec: bytes) -> tuple[tuple[str, Layout, int], ...]:
        plan = self._plans.get(fspec)
        if plan is None:
            present, _ = read_fspec(fspec, 0, len(fspec))
            steps = []
            for k in present:
                entry = self.uap[k] if k < len(self.uap) else None
                if entry is None:
                    raise AsterixError("malformed", f"CAT{self.cat:03d} FSPEC flags FRN {k + 1}, which is spare "
                                                    f"or beyond the UAP (edition {self.edition})")
                name, layout = entry
                steps.append((name, layout, layout.size if isinstance(layout, Fixed) else 0))
            plan = tuple(steps)
            if len(self._plans) < PLAN_CACHE:
                self._plans[fspec] = plan
        return plan

    def split(self, data: bytes, pos: int, end: int) -> tuple[dict[str, bytes], int]:
        """The items of the record at ``pos`` (``name -> raw octets``) and where it ends."""
        start = pos
        while True:  # the FSPEC: octets until one with FX clear
            if pos >= end:
                raise _truncated(f"CAT{self.cat:03d} FSPEC", pos + 1, end)
            pos += 1
            if not data[pos - 1] & 1:
                break
        items: dict[str, bytes] = {}
        for name, layout, size in self._plan(data[start:pos]):
            stop = pos + size if size else layout.end(data, pos, end)
            if stop > end:
                raise _truncated(f"I{self.cat:03d}/{name}", stop, end)
            items[name] = data[pos:stop]
            pos = stop
        if len(items) == 0:
            raise AsterixError("malformed", f"CAT{self.cat:03d} record with an empty FSPEC")
        return items, pos

    def join(self, items: Mapping[str, bytes]) -> bytes:
        """Items by name (None: absent) -> the record: FSPEC and items in FRN order."""
        present = sorted(self.frn[name] for name, v in items.items() if v is not None)
        return write_fspec(present) + b"".join(items[self.uap[k][0]] for k in present)


# ------------------------------------------------------------------ data blocks


def blocks(data: bytes) -> Iterator[tuple[int, bytes]]:
    """``(CAT, records' octets)`` per data block of a datagram. A block header that
    cannot be trusted ends the datagram: AsterixError after the good blocks."""
    pos, n = 0, len(data)
    while pos < n:
        if pos + 3 > n:
            raise AsterixError("truncated", f"{n - pos} octet(s) after the last data block, a header has 3")
        length = (data[pos + 1] << 8) | data[pos + 2]
        if length < 4:
            raise AsterixError("malformed", f"CAT{data[pos]:03d} data block of length {length} (a record needs 4)")
        if pos + length > n:
            raise AsterixError("truncated", f"CAT{data[pos]:03d} data block of length {length}, "
                                            f"{n - pos} octets left in the datagram")
        yield data[pos], data[pos + 3:pos + length]
        pos += length


def block(cat: int, records: list[bytes]) -> bytes:
    """One data block of these records (ValueError past :data:`MAX_BLOCK` octets)."""
    body = b"".join(records)
    n = len(body) + 3
    if n > MAX_BLOCK or not records:
        raise ValueError(f"a data block holds 1 to {MAX_BLOCK} octets of records, not {n - 3}")
    return bytes((cat, n >> 8, n & 0xFF)) + body


# ------------------------------------------------------------------ field conversions


def uint(raw: bytes) -> int:
    return int.from_bytes(raw, "big")


def sint(value: int, bits: int) -> int:
    """Two's complement of the low ``bits`` bits of ``value``."""
    value &= (1 << bits) - 1
    return value - (1 << bits) if value >> (bits - 1) else value


def quantise(x: float, lsb: float, bits: int, signed: bool, what: str, *, saturate: bool = False) -> int:
    """``x / lsb`` rounded to the nearest integer, as ``bits`` bits (two's complement if
    ``signed``); out of range: ValueError, or the extreme (``saturate``: "maximum value
    means maximum value or above")."""
    n = round(x / lsb)
    lo, hi = (-(1 << (bits - 1)), (1 << (bits - 1)) - 1) if signed else (0, (1 << bits) - 1)
    if not lo <= n <= hi:
        if not saturate:
            raise ValueError(f"{what} = {x!r} outside the item's range [{lo * lsb:g}, {hi * lsb:g}]")
        n = min(max(n, lo), hi)
    return n & ((1 << bits) - 1)


def time_of_day(t: float) -> bytes:
    """A time of day (s) -> its three octets of 1/128 s, wrapped at midnight: a time of
    the next day (``t`` ≥ 86 400) is sent as what it is, a time of that day."""
    return (round(t / TOD_LSB) % round(DAY / TOD_LSB)).to_bytes(3, "big")


def wrap(x: float, lsb: float, bits: int) -> int:
    """A circular quantity (an azimuth) -> ``bits`` bits, modulo a full turn."""
    return round(x / lsb) % (1 << bits)


_ICAO = "?ABCDEFGHIJKLMNOPQRSTUVWXYZ????? ???????????????0123456789??????"
_ICAO_CODE = {c: k for k, c in enumerate(_ICAO) if c != "?"}


def icao_chars(raw: bytes) -> str:
    """Eight 6-bit ICAO characters (IA-5 subset) -> text, trailing spaces removed."""
    v = uint(raw)
    return "".join(_ICAO[(v >> (42 - 6 * k)) & 0x3F] for k in range(8)).rstrip()


def icao_bytes(text: str) -> bytes:
    """Text of at most eight of A–Z, 0–9 and space -> six octets (padded with spaces)."""
    text = text.upper()
    if len(text) > 8 or any(c not in _ICAO_CODE for c in text):
        raise ValueError(f"identification {text!r}: at most 8 of A-Z, 0-9 and space")
    v = 0
    for c in text.ljust(8):
        v = (v << 6) | _ICAO_CODE[c]
    return v.to_bytes(6, "big")
