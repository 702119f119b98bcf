"""The processes of a run, in one list: what ``zfusion plan`` prints and ``zfusion run``
starts and supervises (:mod:`services.supervisor`).

:meth:`RunPlan.build` derives every process of a scenario run from the scenario, its
topology and method: a :class:`ProcessSpec` each, with its ``zfusion`` command line, the
processes it waits for and whether it is restarted when killed. In start order:

1. the router, when the processes are started by hand (each a client of it);
2. the fuser (with ``--json``: it prints the result table and writes the summary when
   the sources are done), a regional topology's regional fusers, the recorder (with
   ``--expect``: it stops once every process has reported done, else it runs until
   signalled) and the exporters; with ``--standby``, each fuser's hot standby
   (:func:`standby_id`) once its fuser is up;
3. the local trackers of a distributed, feedback or two-stage method, once the fuser
   is up (they ask it for their initial states);
4. the sources (sensors, the truth clock, jammers), each with ``--wait-for`` its
   consumers, so that nothing it publishes is lost before they listen; ``zfusion run``
   starts them together with a common ``--start-at``.

With ``--asterix-in`` (:class:`Asterix`) the scenario's radars and ADS-B ground stations
send ASTERIX (``zfusion sensor --asterix``) to one ``zfusion ingest asterix`` on a
loopback UDP port, started with the consumers, which publishes their measurements under
their own ids (in a scenario run, ``--scenario-run``: on scenario time, ending their
streams once they are done); both read a copy of the scenario that gives each a SAC/SIC.
The other sensors publish on Zenoh as ever (docs/asterix.md).

Started by hand in that order, they give the numbers ``zfusion run`` gives with the same
scenario, method and seed: the order of the measurements is fixed by their stamps and
watermarks, not by when each process started (docs/deploy.md).
"""

from __future__ import annotations

import json
import math
import shlex
from dataclasses import dataclass
from typing import Mapping, Sequence

from schemas import tracker_id
from schemas.keys import DEFAULT_FUSER


def standby_id(fuser: str) -> str:
    """The process id of ``fuser``'s hot standby (``zfusion run --standby``): ``<fuser>-standby``."""
    return f"{fuser}-standby"


FUSER_ID = DEFAULT_FUSER
STANDBY_ID = standby_id(FUSER_ID)
RECORDER_ID = "recorder"
ASTERIX_ID = "asterix-in"  # the ASTERIX gateway of a run with --asterix-in
ROUTER_ID = "router"
ROLES = ("router", "fuser", "recorder", "exporter", "gateway", "tracker", "source")
# s of silence after which a source is dead at --speed max: nothing is paced there, so a
# source that is silent is far more often starved of CPU (many processes, two cores) than
# dead, and taking it for dead changes what is fused
MAX_SPEED_TIMEOUT = 15.0


@dataclass(frozen=True)
class ProcessSpec:
    """One process of a run.

    Attributes:
        id: its process id (the key of its status and liveliness token).
        role: one of :data:`ROLES`.
        argv: its ``zfusion`` command line, without ``zfusion``.
        waits_for: the processes that must be up (announced on the fabric) before it is
            started; a source also waits for them itself (``--wait-for``).
        restartable: restarted with the same command line when killed from outside.
    """

    id: str
    role: str
    argv: tuple[str, ...]
    waits_for: tuple[str, ...] = ()
    restartable: bool = False

    def __post_init__(self):
        if self.role not in ROLES:
            raise ValueError(f"process {self.id}: role {self.role!r} is not one of {ROLES}")

    @property
    def command(self) -> str:
        return f"zfusion {shlex.join(self.argv)}"


@dataclass(frozen=True)
class Live:
    """What makes the run live (``zfusion run --live``): its fuser's bounded wait and
    re-filtering window; ``endless``: the sources play until stopped."""

    max_delay: float = 1.0
    oosm_window: float = 10.0
    endless: bool = False


@dataclass(frozen=True)
class Asterix:
    """A run's sensors that send ASTERIX: ``site`` the scenario file that gives each a
    SAC/SIC (:func:`services.ingest.asterix.with_sac_sic`), ``udp`` the gateway's
    ``HOST:PORT``, ``sensors`` their ids."""

    site: str
    udp: str
    sensors: tuple[str, ...]


@dataclass(frozen=True)
class RunPlan:
    """The processes of one run, in start order (module docstring)."""

    scenario_name: str
    topology: str
    method: str
    seed: int
    specs: tuple[ProcessSpec, ...]

    @classmethod
    def build(cls, scenario_ref: str, scenario, topology: str, method: str, *, fabric: list[str],
              speed: str = "1", rrd: str = "site.rrd", json_path: str | None = None, router: str | None = None,
              supervisor: str | None = None, settings: Sequence[tuple[str, object]] = (),
              fusion_rule: str | None = None,
              duration: float | None = None, live: Live | None = None, spawn: bool = False,
              rotate_s: float | None = None, outputs: Mapping[str, tuple[str, str, list[str]]] = {},
              standby: bool = False, asterix: Asterix | None = None) -> "RunPlan":
        """The run of ``scenario`` (loaded from ``scenario_ref``) by ``method`` in ``topology``.

        Args:
            fabric: the options every process but the router joins Zenoh with.
            speed: the sources' ``--speed`` (``"max"`` or a number).
            rrd: the recorder's file; json_path: the fuser writes the summary there.
            router: the endpoint of a router to start first (by hand), else none.
            supervisor: the id of the process that starts the sources, which they also
                wait for (``zfusion run``'s launcher).
            settings: ``[tracker]`` overrides (``--set``); fusion_rule: ``--fusion-rule``.
            duration: a duration given on the command line (it replaces the scenario's).
            live: a live session; spawn, rotate_s: the recorder's ``--spawn``, ``--rotate-s``.
            outputs: exporters, process id -> (name, option, value) of
                :data:`services.export.outputs.OUTPUTS`.
            standby: a hot standby of the fuser, :data:`STANDBY_ID`, and of each regional
                fuser, :func:`standby_id` of its region (:mod:`services.leader`).
            asterix: sensors that send ASTERIX to a gateway, :data:`ASTERIX_ID`.
        """
        timeout = source_timeout(scenario, speed)
        seed = ["--seed", str(scenario.seed)]
        dur = ["--duration-s", repr(scenario.duration)] if duration is not None else []
        # what the fuser, trackers and recorder are given: the scenario (with its overrides), or live its site
        given = ["--site", scenario_ref] if live else ["--scenario", scenario_ref, *seed, *dur]
        tuned = [a for k, v in settings for a in ("--set", f"{k}={json.dumps(v)}")]
        tuned += ["--fusion-rule", fusion_rule] if fusion_rule else []
        split = topology not in ("centralised", "regional")
        trackers = {s: tracker_id(s) for s in scenario.sensors} if split else {}
        regions = dict(scenario.regions) if topology == "regional" else {}  # region -> its fuser, of that id
        sources = list(scenario.process_ids())
        standbys = [standby_id(f) for f in (*regions, FUSER_ID)] if standby else []
        specs = [ProcessSpec(ROUTER_ID, "router", ("router", "--listen", router))] if router else []
        specs.append(ProcessSpec(FUSER_ID, "fuser", (
            "fuser", *given, "--method", method, "--id", FUSER_ID, *(["--system"] if regions else []),
            "--source-timeout", str(timeout), *tuned,
            *(["--max-delay", repr(live.max_delay), "--oosm-window", repr(live.oosm_window)] if live else []),
            *(["--json", json_path] if json_path else []), *fabric), restartable=True))
        for region in regions:  # each region's fuser, the system fuser's sources
            specs.append(ProcessSpec(region, "fuser", (
                "fuser", *given, "--method", method, "--region", region, "--source-timeout", str(timeout), *tuned,
                *fabric), restartable=True))
        for region in regions if standby else ():  # its frames again, published only once its fuser is gone
            specs.append(ProcessSpec(standby_id(region), "fuser", (
                "fuser", *given, "--method", method, "--region", region, "--id", standby_id(region),
                "--standby", region, "--source-timeout", str(timeout), *tuned, *fabric),
                waits_for=(region,), restartable=True))  # started after: the younger (services/leader.py)
        if standby:  # the fuser's work again, published only when the fuser's process is gone
            specs.append(ProcessSpec(STANDBY_ID, "fuser", (
                "fuser", *given, "--method", method, "--id", STANDBY_ID, "--standby", FUSER_ID,
                *(["--system"] if regions else []),
                "--source-timeout", str(timeout), *tuned,
                *(["--max-delay", repr(live.max_delay), "--oosm-window", repr(live.oosm_window)] if live else []),
                *fabric), waits_for=(FUSER_ID,), restartable=True))  # started after: the younger (services/leader.py)
        specs.append(ProcessSpec(RECORDER_ID, "recorder", (
            "record", "--rrd", rrd, "--id", RECORDER_ID, *given, *(["--spawn"] if spawn else []),
            *(["--rotate-s", str(rotate_s)] if rotate_s else []),
            "--expect", ",".join([FUSER_ID, *regions, *standbys, *trackers.values(), *sources,
                                  *([ASTERIX_ID] if asterix and not live else [])]), *fabric), restartable=True))
        for pid, (name, option, value) in outputs.items():  # listeners like the recorder, up before the sources
            specs.append(ProcessSpec(pid, "exporter", (
                "export", name, option, value, "--site" if live else "--scenario", scenario_ref, "--id", pid, *fabric),
                restartable=True))
        def fed(sid: str) -> list[str]:
            """Who takes ``sid``'s measurements: the regions it feeds and the system fuser
            their frames go to (regional), its tracker, or the fuser."""
            return [*(r for r, reg in regions.items() if sid in reg.sensors), FUSER_ID] if regions \
                else [trackers.get(sid, FUSER_ID)]

        if asterix is not None:  # a gateway for the scenario's radars and stations, up before they send
            takers = dict.fromkeys([*(p for sid in asterix.sensors for p in fed(sid)), RECORDER_ID])
            specs.append(ProcessSpec(ASTERIX_ID, "gateway", (
                "ingest", "asterix", "--id", ASTERIX_ID, "--site", asterix.site, "--udp", asterix.udp,
                *([] if live else ["--scenario-run", ",".join(asterix.sensors)]), "--wait-for", ",".join(takers),
                *fabric), waits_for=tuple(takers)))
        for sensor, tid in trackers.items():
            specs.append(ProcessSpec(tid, "tracker", (
                "tracker", *given, "--sensor", sensor, "--method", method, "--fuser", FUSER_ID,
                "--feedback-timeout", str(timeout), *tuned, *fabric), waits_for=(FUSER_ID,), restartable=True))
        for sid in sources:
            # A source waits only for its consumers: the fuser may finish (and vanish)
            # before a truth or jammer process discovers it, so they must not wait for it.
            consumers = [*fed(sid), RECORDER_ID] if sid in scenario.sensors else [RECORDER_ID]
            sends = asterix is not None and sid in asterix.sensors  # ASTERIX to the gateway, not on Zenoh
            consumers += [ASTERIX_ID] if sends else []
            # a live emulation plays the scenario's duration (else until stopped, if endless)
            played = ["--duration-s", repr(scenario.duration)] if dur or (live and not live.endless) else []
            specs.append(ProcessSpec(sid, "source", (
                "sensor", "--scenario", asterix.site if sends else scenario_ref, *seed, *played, "--id", sid,
                "--speed", str(speed), *(["--live"] if live else []),
                *(["--asterix", f"udp://{asterix.udp}"] if sends else []),
                "--wait-for", ",".join([*consumers, *([supervisor] if supervisor else [])]), *fabric),
                waits_for=tuple(consumers)))
        return cls(scenario.name, topology, method, scenario.seed, tuple(specs))

    def __iter__(self):
        return iter(self.specs)

    def of_role(self, *roles: str) -> list[ProcessSpec]:
        return [s for s in self.specs if s.role in roles]

    def ids(self, *roles: str) -> list[str]:
        return [s.id for s in self.of_role(*roles)]

    def __getitem__(self, pid: str) -> ProcessSpec:
        return next(s for s in self.specs if s.id == pid)

    def format(self) -> str:
        """The plan as ``zfusion plan`` prints it: a comment line and a command per process."""
        routers = len(self.of_role("router"))
        lines = [f"# scenario {self.scenario_name} · topology {self.topology} · method {self.method} · "
                 f"seed {self.seed} · {len(self.specs) - routers} processes" + (" and a router" if routers else ""),
                 "# start each in its own shell (or end it with &), in this order; the fuser prints the result"]
        for spec in self.specs:
            lines += [f"# {spec.id}", spec.command]
        return "\n".join(lines)


def source_timeout(scenario, speed: str) -> float:
    """Seconds of silence after which the fuser takes a source for dead: three of the
    slowest sensor's scan periods of wall time, at least 3 s (``--speed max``:
    :data:`MAX_SPEED_TIMEOUT`)."""
    pace = math.inf if speed == "max" else float(speed)
    max_period = max([getattr(s, "period", 1.0) for s in scenario.sensors.values()] + [1.0])
    return MAX_SPEED_TIMEOUT if math.isinf(pace) else max(3.0, 3.0 * max_period / pace)
