"""The Zenoh key space, in one place (docs/design.md, "Key space").

Every key lives under ``zf/<deployment>/``. Ids (sensors, nodes, processes, targets)
become single key chunks, so they are restricted to ``[A-Za-z0-9_.+-]``: no ``/`` and
none of Zenoh's wildcard or verbatim characters.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

ROOT = "zf"
DEFAULT_DEPLOYMENT = "default"
_ID = re.compile(r"^[A-Za-z0-9_.+-]{1,64}$")


def check_id(value: str, what: str = "id") -> str:
    if not isinstance(value, str) or not _ID.match(value):
        raise ValueError(f"{what} {value!r}: must be 1-64 characters of [A-Za-z0-9_.+-]")
    return value


TRACKER_PREFIX = "trk-"
DEFAULT_FUSER = "fuser"  # the id of a deployment's fuser unless it is given another


def tracker_id(sensor: str) -> str:
    """Process id (and ``local/``/``feedback/`` key id) of a sensor's local tracker."""
    return check_id(TRACKER_PREFIX + sensor, "tracker id")


@dataclass(frozen=True)
class KeySpace:
    deployment: str = DEFAULT_DEPLOYMENT

    def __post_init__(self) -> None:
        check_id(self.deployment, "deployment")

    @property
    def prefix(self) -> str:
        return f"{ROOT}/{self.deployment}"

    def _key(self, family: str, ident: str | None = None) -> str:
        if ident is None:
            return f"{self.prefix}/{family}"
        return f"{self.prefix}/{family}/{check_id(ident)}"

    def meas(self, sensor: str) -> str:
        return self._key("meas", sensor)

    def jam(self, jammer: str) -> str:
        return self._key("jam", jammer)

    def local(self, node: str) -> str:
        return self._key("local", node)

    def feedback(self, node: str) -> str:
        return self._key("feedback", node)

    def fused(self, fuser: str) -> str:
        """The tracks of the fuser ``fuser`` (its id, which a hot standby publishes under
        too); ``*`` every fuser's. A track is named by its fuser and its id there, so
        fusers (regional centres, a system centre) publish side by side."""
        return self._key("fused", fuser) if fuser != "*" else f"{self.prefix}/fused/*"

    def regional(self, region: str) -> str:
        """A regional fuser's frames (``regional_frame``, watermarks), for the system fuser
        above it (:mod:`fusion.regional`): not tracks for display, so not on ``fused/``."""
        return self._key("regional", region)

    def picture(self, fuser: str) -> str:
        """A fuser's queryable: its current tracks, for late joiners (services.picture);
        ``*`` every fuser's."""
        return self._key("picture", fuser) if fuser != "*" else f"{self.prefix}/picture/*"

    def truth(self, target: str) -> str:
        return self._key("truth", target)

    def status(self, process: str) -> str:
        return self._key("status", process)

    def alive(self, process: str, incarnation: str = "*") -> str:
        """Liveliness token of one incarnation of a process (its Zenoh session id),
        present while that session is open; ``*`` watches every incarnation.

        The incarnation is in the key because Zenoh merges tokens on the same key: a
        restarted process that declares its token before the loss of the old one is
        noticed would otherwise be seen neither to go nor to come back."""
        inc = incarnation if incarnation == "*" else check_id(incarnation, "incarnation")
        return f"{self._key('alive', process)}/{inc}"

    def all(self, family: str | None = None) -> str:
        """Wildcard over one family (``meas``, ``status``, ...) or the whole deployment."""
        return f"{self.prefix}/{family}/**" if family else f"{self.prefix}/**"

    def alive_process(self, key: str) -> tuple[str, str]:
        """(process, incarnation) of a concrete liveliness token key."""
        family, process = self.family_and_id(key)
        parts = key.split("/")
        if family != "alive" or process is None or len(parts) != 5:
            raise ValueError(f"key {key!r} is not a liveliness token of {self.prefix}/")
        return process, parts[4]

    def family_and_id(self, key: str) -> tuple[str, str | None]:
        """Split a concrete key of this deployment into (family, id)."""
        parts = key.split("/")
        if len(parts) < 3 or parts[0] != ROOT or parts[1] != self.deployment:
            raise ValueError(f"key {key!r} is not under {self.prefix}/")
        return parts[2], (parts[3] if len(parts) > 3 else None)
