"""Support for the tests of deployments across hosts: the deployment files, a router to
wait for, the test's own view of the fabric, and the processes of one site as an operator
starts them."""

from __future__ import annotations

import socket
import threading
import time
from contextlib import contextmanager
from pathlib import Path

import zenoh

from schemas import KeySpace, decode, to_estimate, tracker_id
from schemas.keys import DEFAULT_FUSER
from services.launcher import free_port
from services.node import ZenohOptions
from services.scoring import truth_function
from services.supervisor import Children
from services.summary import method_summary


DEPLOY = Path(__file__).resolve().parents[1] / "deploy"


ZENOH = DEPLOY / "zenoh"


ROUTER_HOST = "127.0.0.1"


def wait_listening(host: str, port: int, proc, timeout: float = 30.0) -> None:
    """Block until something accepts TCP connections on host:port (the router is up)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        assert proc.poll() is None, f"router exited with {proc.returncode}"
        with socket.socket() as s:
            if s.connect_ex((host, port)) == 0:
                return
        time.sleep(0.05)
    raise AssertionError(f"nothing listens on {host}:{port} after {timeout} s")


class Watcher:
    """The test's own view of the fabric: a Zenoh session that records everything under
    the deployment's prefix and can announce itself, so that sources start only once it
    listens (they ``--wait-for`` it like a consumer)."""

    NAME = "watcher"

    def __init__(self, config: zenoh.Config, keys: KeySpace):
        self.keys = keys
        self.samples: list[tuple[str, bytes]] = []
        self.session = zenoh.open(config)
        self._sub = self.session.declare_subscriber(keys.all(), self._on_sample)
        self._token = None

    def _on_sample(self, sample: zenoh.Sample) -> None:
        self.samples.append((str(sample.key_expr), sample.payload.to_bytes()))

    def announce(self, name: str = NAME) -> None:
        self._token = self.session.liveliness().declare_token(self.keys.alive(name, str(self.session.zid())))

    def wait_alive(self, name: str, timeout: float) -> bool:
        """Whether process ``name`` announces itself within ``timeout`` seconds."""
        seen = threading.Event()
        sub = self.session.liveliness().declare_subscriber(self.keys.alive(name), lambda _: seen.set(), history=True)
        try:
            return seen.wait(timeout)
        finally:
            sub.undeclare()

    def messages(self, key: str) -> list:
        return [decode(data) for k, data in list(self.samples) if k == key]

    decode = staticmethod(decode)

    def wait_fused(self, n: int, timeout: float = 5.0, fuser: str = DEFAULT_FUSER) -> None:
        """Until ``n`` of ``fuser``'s samples are in (the last ones may still be crossing the router)."""
        deadline = time.monotonic() + timeout
        while len(self.messages(self.keys.fused(fuser))) < n and time.monotonic() < deadline:
            time.sleep(0.05)

    def summary(self, scenario, fuser: str = DEFAULT_FUSER) -> dict:
        estimates = [to_estimate(m) for m in self.messages(self.keys.fused(fuser)) if m.kind == "track"]
        return method_summary([estimates], truth_function(scenario))

    def close(self) -> None:
        self.session.close()


def site(scenario, method: str, topology: str, watcher: str = Watcher.NAME) -> dict[str, list[str]]:
    """The processes of one site, as an operator would start them on their hosts (without
    fabric options). Sources wait for their consumer and for ``watcher``."""
    common = ["--scenario", scenario.name]
    procs = {"fuser": ["fuser", *common, "--method", method, "--id", "fuser"]}
    consumer = {s: "fuser" for s in scenario.sensors}
    if topology != "centralised":
        for s in scenario.sensors:
            procs[tracker_id(s)] = ["tracker", *common, "--sensor", s, "--method", method, "--fuser", "fuser"]
            consumer[s] = tracker_id(s)
    for s in scenario.sensors:
        procs[s] = ["sensor", *common, "--id", s, "--speed", "max", "--wait-for", f"{consumer[s]},{watcher}"]
    return procs


@contextmanager
def behind_a_router(deployment: str, scenario_ref: str):
    """A router on a free loopback port, the test's :class:`Watcher` as its client, and
    the processes the test starts (``Children``; stopped at the end, the watcher
    closed): yields ``(children, watcher, common)``, ``common`` the options every
    process is given (the scenario, the deployment, the router as a client)."""
    port = free_port()
    ep = f"tcp/{ROUTER_HOST}:{port}"
    client = ZenohOptions(connect=[ep], mode="client")
    children = Children()
    watcher = None
    try:
        children.start("router", ["router", "--listen", ep])
        wait_listening(ROUTER_HOST, port, children.procs["router"])
        watcher = Watcher(client.to_config(), KeySpace(deployment))
        yield children, watcher, ["--scenario", scenario_ref, "--deployment", deployment, *client.to_args()]
    finally:
        if watcher is not None:
            watcher.close()
        children.stop_all()
