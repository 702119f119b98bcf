"""CAT065 (SDPS service status reports), edition 1.6: a tracker's heartbeat beside its
CAT062 tracks.

Written and read (:class:`SdpsStatus`): I065/010 SAC/SIC, /000 message type (1 SDPS
status, 2 end of batch, 3 service status report), /015 service identification, /030
time of message (1/128 s), /020 batch number, /040 SDPS configuration and status
(NOGO: 0 operational, 1 degraded, 2 not connected, 3 unknown; OVL overload; TSV time
source invalid; PSS selected SDPS 0–3; STTN track re-numbering), /050 service status
report (1 degradation ... 16: main and backup radar failed).
"""

from __future__ import annotations

from dataclasses import dataclass

from .framing import Category, Explicit, Fixed, time_of_day, uint
from .units import TOD_LSB

CATEGORY = Category(65, "1.6", (
    ("010", Fixed(2)), ("000", Fixed(1)), ("015", Fixed(1)), ("030", Fixed(3)), ("020", Fixed(1)),
    ("040", Fixed(1)), ("050", Fixed(1)), None, None, None, None, None, ("RE", Explicit()), ("SP", Explicit()),
))

SDPS_STATUS = 1
END_OF_BATCH = 2
SERVICE_STATUS = 3


@dataclass(frozen=True, slots=True)
class SdpsStatus:
    sac: int
    sic: int
    message_type: int
    service: int
    tod: float
    batch: int | None = None
    nogo: int | None = None  # I065/040 present when not None
    ovl: bool = False
    tsv: bool = False
    pss: int = 0
    sttn: bool = False
    report: int | None = None

    category = 65


def decode(items: dict[str, bytes]) -> SdpsStatus:
    g = items.get
    if any(g(k) is None for k in ("010", "000", "015", "030")):
        raise ValueError("a CAT065 message needs I065/010, /000, /015 and /030")
    kw: dict = {"sac": g("010")[0], "sic": g("010")[1], "message_type": g("000")[0], "service": g("015")[0],
                "tod": uint(g("030")) * TOD_LSB}
    if (b := g("020")) is not None:
        kw["batch"] = b[0]
    if (b := g("040")) is not None:
        o = b[0]
        kw.update(nogo=o >> 6, ovl=bool(o & 0x20), tsv=bool(o & 0x10), pss=(o >> 2) & 3, sttn=bool(o & 0x02))
    if (b := g("050")) is not None:
        kw["report"] = b[0]
    return SdpsStatus(**kw)


def encode(m: SdpsStatus) -> bytes:
    items: dict[str, bytes] = {"010": bytes((m.sac, m.sic)), "000": bytes((m.message_type,)),
                               "015": bytes((m.service,)), "030": time_of_day(m.tod)}
    if m.batch is not None:
        items["020"] = bytes((m.batch & 0xFF,))
    if m.nogo is not None:
        items["040"] = bytes(((m.nogo << 6) | (m.ovl << 5) | (m.tsv << 4) | (m.pss << 2) | (m.sttn << 1),))
    if m.report is not None:
        items["050"] = bytes((m.report,))
    return CATEGORY.join(items)
