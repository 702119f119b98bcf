"""Reading TOML tables with validation and ``file:line: field: why`` errors.

``tomllib`` returns plain dicts without positions, so :class:`TomlSource` finds the
line of a field by searching the source text: the table header (``[a.b]``, or the n-th
``[[a.b]]`` for an array of tables), then the key inside that table (bare, quoted or
dotted). A field that is missing is reported at its table's header. :class:`Reader`
walks one table, converts unit-suffixed keys to SI and rejects keys it never read.
"""

from __future__ import annotations

import difflib
import math
import re
from typing import Any, Iterator

import numpy as np

from .spec import ScenarioError

REQUIRED: Any = object()  # sentinel: the key must be present

# Unit suffixes a key may carry, and their factor to SI.
LENGTH = {"m": 1.0, "km": 1000.0}
ANGLE = {"rad": 1.0, "deg": math.pi / 180.0}
TIME = {"s": 1.0}
RATE = {"rad_s": 1.0, "deg_s": math.pi / 180.0}

_HEADER = re.compile(r"^\s*(\[\[?)\s*(.+?)\s*\]\]?\s*$")
_COMMENT = re.compile(r"\s*#[^\"']*$")  # a trailing comment (without quotes in it)
_STRING = re.compile(r'"(?:[^"\\]|\\.)*"|\'[^\']*\'')


def _split_dotted(key: str) -> tuple[str, ...]:
    """``a."b.c".d`` -> ("a", "b.c", "d")."""
    parts = re.findall(r'\s*("[^"]*"|\'[^\']*\'|[^.]+)\s*(?:\.|$)', key)
    return tuple(p.strip().strip("\"'") for p in parts)


def format_path(path: tuple) -> str:
    out = ""
    for p in path:
        out += f"[{p}]" if isinstance(p, int) else (f".{p}" if out else str(p))
    return out or "<top level>"


class TomlSource:
    """The text of one TOML file, to find the line a field is on."""

    def __init__(self, text: str, name: str):
        self.name = name
        self.lines = text.splitlines()
        # (line index, dotted key, is array of tables), in file order
        self.headers: list[tuple[int, tuple[str, ...], bool]] = []
        depth = 0  # bracket depth of a multi-line value: "[1, 2]" there is no header
        for i, line in enumerate(self.lines):
            bare = _STRING.sub('""', line).split("#", 1)[0]
            m = _HEADER.match(_COMMENT.sub("", line)) if depth == 0 and _HEADER.match(bare) else None
            if m:
                self.headers.append((i, _split_dotted(m.group(2)), m.group(1) == "[["))
            else:
                depth += bare.count("[") + bare.count("{") - bare.count("]") - bare.count("}")

    def _region(self, prefix: tuple) -> tuple[int, int, int] | None:
        """(header line, first body line, end line) of the table ``prefix``, or None."""
        if not prefix:
            end = self.headers[0][0] if self.headers else len(self.lines)
            return (0, 0, end)
        if isinstance(prefix[-1], int):  # the n-th [[a.b]]
            keys, want, is_array = prefix[:-1], prefix[-1], True
        else:
            keys, want, is_array = prefix, 0, False
        if not all(isinstance(k, str) for k in keys):
            return None
        seen = 0
        for j, (line, hkeys, harray) in enumerate(self.headers):
            if hkeys == keys and harray == is_array:
                if seen == want:
                    end = self.headers[j + 1][0] if j + 1 < len(self.headers) else len(self.lines)
                    return (line, line + 1, end)
                seen += 1
        return None

    def _key_line(self, lo: int, hi: int, keys: tuple) -> int | None:
        names = []
        for k in keys:
            if not isinstance(k, str):
                break
            names.append(k)
        for j in range(len(names), 0, -1):  # the longest dotted key that is written
            pat = r"\s*\.\s*".join(f"(?:{re.escape(k)}|\"{re.escape(k)}\"|'{re.escape(k)}')" for k in names[:j])
            rx = re.compile(rf"^\s*{pat}\s*=")
            for i in range(lo, hi):
                if rx.match(self.lines[i]):
                    return i
        return None

    def line_of(self, path: tuple) -> int:
        """1-based line of ``path`` (its key, else its nearest table header, else 1)."""
        fallback = None
        for k in range(len(path), -1, -1):
            region = self._region(path[:k])
            if region is None:
                continue
            header, lo, hi = region
            if k == len(path):
                return header + 1 if k else 1
            line = self._key_line(lo, hi, path[k:])
            if line is not None:
                return line + 1
            if fallback is None:
                fallback = header + 1 if k else 1
        return fallback or 1

    def error(self, path: tuple, message: str) -> ScenarioError:
        return ScenarioError(f"{self.name}:{self.line_of(path)}: {format_path(path)}: {message}")


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


class Reader:
    """One table of the file being loaded: typed, bounded reads with located errors.

    Every read marks its key as used; :meth:`finish` rejects the keys nobody read.
    """

    def __init__(self, data: dict, path: tuple, source: TomlSource):
        self.data = data
        self.path = path
        self.source = source
        self._known: set[str] = set()

    def error(self, message: str, key: str | int | None = None) -> ScenarioError:
        return self.source.error(self.path + (() if key is None else (key,)), message)

    def has(self, key: str) -> bool:
        return key in self.data

    def allow(self, *keys: str) -> None:
        """Declare keys valid here even if this read path did not use them."""
        self._known.update(keys)

    def _misspelt(self, wanted: list[str]) -> str:
        """A note naming a key of this table that looks like a misspelling of one of
        ``wanted`` (a key nobody reads here, close to it), or ``""``."""
        strays = [k for k in self.data if isinstance(k, str) and k not in self._known and k not in wanted]
        for w in wanted:
            close = difflib.get_close_matches(w, strays, n=1, cutoff=0.85)
            if close:
                return f"; '{close[0]}' is given: a misspelling of '{w}'?"
        return ""

    def raw(self, key: str, default=REQUIRED):
        self._known.add(key)
        if key not in self.data:
            if default is REQUIRED:
                raise self.error(f"missing (required{self._misspelt([key])})", key)
            return default
        return self.data[key]

    def table(self, key: str, required: bool = True) -> Reader | None:
        v = self.raw(key, REQUIRED if required else None)
        if v is None:
            return None
        if not isinstance(v, dict):
            raise self.error("must be a table", key)
        return Reader(v, self.path + (key,), self.source)

    def tables(self, key: str, required: bool = True) -> Iterator[tuple[str, Reader]]:
        """The sub-tables of table ``key`` (``[key.<id>]``), as (id, reader)."""
        outer = self.table(key, required)
        if outer is None:
            return
        if not outer.data and required:
            raise self.error("must define at least one entry", key)
        for name, v in outer.data.items():
            outer._known.add(name)
            if not isinstance(v, dict):
                raise outer.error("must be a table", name)
            yield name, Reader(v, outer.path + (name,), self.source)

    def array_of_tables(self, key: str) -> list[Reader] | None:
        v = self.raw(key, None)
        if v is None:
            return None
        if not isinstance(v, list) or not v or not all(isinstance(e, dict) for e in v):
            raise self.error("must be a non-empty array of tables", key)
        return [Reader(e, self.path + (key, i), self.source) for i, e in enumerate(v)]

    def string(self, key: str, default=REQUIRED, choices: tuple[str, ...] | None = None) -> str:
        v = self.raw(key, default)
        if v is default and default is not REQUIRED:
            return v
        if not isinstance(v, str) or not v:
            raise self.error("must be a non-empty string", key)
        if choices is not None and v not in choices:
            raise self.error(f"must be one of {', '.join(choices)} (got {v!r})", key)
        return v

    def integer(self, key: str, default=REQUIRED, **bounds) -> int:
        v = self.raw(key, default)
        if v is default and default is not REQUIRED:
            return v
        if not isinstance(v, int) or isinstance(v, bool):
            raise self.error("must be an integer", key)
        self._check_bounds(key, v, **bounds)
        return v

    def number(self, key: str, default=REQUIRED, *, allow_inf: bool = False, **bounds) -> float:
        v = self.raw(key, default)
        if v is default and default is not REQUIRED:
            return v
        return self._number(key, v, allow_inf, **bounds)

    def _number(self, key, v, allow_inf=False, **bounds) -> float:
        if not _is_number(v) or math.isnan(v) or (math.isinf(v) and not allow_inf):
            raise self.error("must be a finite number" if not allow_inf else "must be a number", key)
        self._check_bounds(key, v, **bounds)
        return float(v)

    def _check_bounds(self, key, v, gt=None, ge=None, lt=None, le=None, ne=None):
        for bound, ok, op in ((gt, lambda: v > gt, ">"), (ge, lambda: v >= ge, ">="),
                              (lt, lambda: v < lt, "<"), (le, lambda: v <= le, "<="),
                              (ne, lambda: v != ne, "!=")):
            if bound is not None and not ok():
                raise self.error(f"must be {op} {bound:g} (got {v:g})", key)

    def unit_key(self, base: str, units: dict[str, float], required: bool = True) -> str | None:
        """Which of ``base_<unit>`` is given (exactly one, or none if not required)."""
        variants = [f"{base}_{u}" for u in units]
        self._known.update(variants)
        given = [k for k in variants if k in self.data]
        if len(given) > 1:
            raise self.error(f"give only one of {', '.join(given)}", given[1])
        if not given:
            if required:
                alternatives = f"; or {' or '.join(variants[1:])}" if len(variants) > 1 else ""
                raise self.error(f"missing (required{alternatives}{self._misspelt(variants)})", variants[0])
            return None
        return given[0]

    def quantity(self, base: str, units: dict[str, float], default=REQUIRED, *,
                 allow_inf: bool = False, **bounds) -> float:
        """A scalar given as ``base_<unit>``, converted to SI (bounds in the given unit)."""
        key = self.unit_key(base, units, required=default is REQUIRED)
        if key is None:
            return default
        factor = units[key[len(base) + 1:]]
        return self._number(key, self.data[key], allow_inf, **bounds) * factor

    def vector(self, key: str, lengths: tuple[int, ...], factor: float = 1.0,
               min_rows: int | None = None, default=REQUIRED) -> np.ndarray:
        """A list of numbers (``min_rows`` None) or a list of such lists, each of one of
        ``lengths``; 2-vectors where 3 are allowed get a zero third component."""
        v = self.raw(key, default)
        if v is default and default is not REQUIRED:
            return v
        rows = [v] if min_rows is None else v
        if min_rows is not None and (not isinstance(v, list) or len(v) < min_rows):
            raise self.error(f"must be a list of at least {min_rows} points", key)
        out = []
        for row in rows:
            if (not isinstance(row, list) or len(row) not in lengths
                    or not all(_is_number(e) and math.isfinite(e) for e in row)):
                want = " or ".join(str(n) for n in lengths)
                raise self.error(f"must be {'points of ' if min_rows else ''}{want} finite numbers", key)
            row = [float(e) for e in row]
            out.append(row + [0.0] * (max(lengths) - len(row)))
        a = np.array(out) * factor
        return a if min_rows is not None else a[0]

    def unit_vector(self, base: str, units: dict[str, float], lengths: tuple[int, ...],
                    required: bool = True, min_rows: int | None = None) -> tuple[np.ndarray | None, str | None]:
        """A vector (or list of points) given as ``base_<unit>``, in SI, and its key."""
        key = self.unit_key(base, units, required)
        if key is None:
            return None, None
        return self.vector(key, lengths, units[key[len(base) + 1:]], min_rows), key

    def finish(self) -> None:
        unknown = [k for k in self.data if k not in self._known]
        if unknown:
            close = difflib.get_close_matches(str(unknown[0]), sorted(self._known), n=1, cutoff=0.75)
            hint = f"did you mean '{close[0]}'? " if close else ""
            raise self.error(f"unknown key ({hint}allowed here: {', '.join(sorted(self._known)) or 'none'})",
                             unknown[0])
