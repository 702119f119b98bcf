"""Multi-host deployment: every process a Zenoh *client* of one router, each on its own
loopback address (as if on its own host), talking only through the router; the fused
output equals the in-process evaluation (and so the peer-to-peer run) to 1e-9. Plus the
deployment files (deploy/): Zenoh configs load, the compose file parses, and every
command in the compose file and the systemd units is one the CLI accepts."""

from __future__ import annotations

import json
import re
import shlex
import time
from pathlib import Path

import psutil
import pytest
import zenoh

from schemas import KeySpace, tracker_id
from services.cli import build_parser
from services.launcher import free_port
from services.supervisor import Children
from services.node import ZenohOptions
from sensors_sim import load_scenario

from _runs import in_process, same_series
from _multihost import DEPLOY, ROUTER_HOST, Watcher, ZENOH, site, wait_listening

def _client(ep: str, addr: str) -> ZenohOptions:
    """A client of the router at ``ep`` (deploy/zenoh/client.json5), dialling from ``addr``."""
    return ZenohOptions(config_file=str(ZENOH / "client.json5"), connect=[f"{ep}#bind={addr}:0"])


def _wait_connected(pids: dict[str, int], timeout: float = 40.0) -> dict[str, list]:
    """Every process's internet sockets, once each has its link to the router."""
    deadline = time.monotonic() + timeout
    while True:
        socks = {n: psutil.Process(pid).net_connections("inet") for n, pid in pids.items()}
        if all(any(c.status == psutil.CONN_ESTABLISHED for c in cs) for cs in socks.values()):
            return socks
        if time.monotonic() > deadline:
            raise AssertionError(f"not connected after {timeout} s: {[n for n, c in socks.items() if not c]}")
        time.sleep(0.1)


@pytest.mark.slow
@pytest.mark.parametrize("topology,method", [("centralised", "SS"), ("feedback", "PHHNV")])
def test_clients_of_a_router_on_distinct_addresses_equalin_process(deployment, topology, method):
    scenario = load_scenario("patent-3d")
    keys = KeySpace(deployment)
    port = free_port()
    ep = f"tcp/{ROUTER_HOST}:{port}"
    plan = site(scenario, method, topology)
    ref = in_process("patent-3d", method)
    addrs = {name: f"127.0.0.{i + 2}" for i, name in enumerate([*plan, Watcher.NAME])}  # one "host" each
    children = Children()
    watcher = None
    try:
        children.start("router", ["router", "--zenoh-config", str(ZENOH / "router.json5"), "--listen", ep])
        wait_listening(ROUTER_HOST, port, children.procs["router"])
        watcher = Watcher(_client(ep, addrs[Watcher.NAME]).to_config(), keys)
        for name, argv in plan.items():
            children.start(name, [*argv, "--deployment", deployment, *_client(ep, addrs[name]).to_args()])

        # Before anything flows: each process has exactly one link, from its own address to
        # the router, and listens nowhere: it can only talk through the router.
        socks = _wait_connected({n: children.procs[n].pid for n in plan})
        for name, conns in socks.items():
            assert [(c.laddr.ip, tuple(c.raddr), c.status) for c in conns] == [
                (addrs[name], (ROUTER_HOST, port), psutil.CONN_ESTABLISHED)], (name, conns)
        peers = {c.raddr.ip for c in psutil.Process(children.procs["router"].pid).net_connections("inet")
                 if c.status == psutil.CONN_ESTABLISHED and c.laddr.port == port}
        assert peers == set(addrs.values())

        watcher.announce()  # the sources wait for it: the scenario starts now
        assert children.wait("fuser", 60.0) == 0
        for name in plan:
            assert children.wait(name, 20.0) == 0, name
        watcher.wait_fused(ref["n_updates"])
        got = watcher.summary(scenario)
    finally:
        if watcher is not None:
            watcher.close()
        children.stop_all()
    same_series(got, ref)
    assert children.procs["router"].returncode == 0  # SIGTERM: a clean stop


# --- the deployment files -----------------------------------------------------------


@pytest.mark.parametrize("path", sorted(ZENOH.glob("*.json5")), ids=lambda p: p.name)
def test_zenoh_configs_load(path):
    conf = zenoh.Config.from_file(str(path))  # the installed zenoh parses and validates it
    mode = json.loads(conf.get_json("mode"))
    assert mode == path.stem.split("-")[0]  # peer.json5 is a peer, client-tls.json5 a client, ...
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    tls = "tls" in path.stem
    assert json.loads(conf.get_json("transport/link/protocols")) == (["tls"] if tls else None)
    if tls:
        assert json.loads(conf.get_json("transport/link/tls/enable_mtls")) is True
    acl = json.loads(conf.get_json("access_control"))
    assert acl["enabled"] is ("acl" in path.stem)


def test_no_key_material_in_the_repository():
    """Certificates and keys are made on site (deploy/make-certs.sh, into deploy/certs/,
    which git ignores) or by the tests, never committed."""
    assert "certs/" in (DEPLOY / ".gitignore").read_text().split()
    files = [p for d in (DEPLOY, DEPLOY.parent / "docs") for p in d.rglob("*")
             if p.is_file() and not p.is_relative_to(DEPLOY / "certs")]
    assert not [p for p in files if p.suffix in (".key", ".pem", ".crt", ".p12")]
    assert not [p for p in files if p.suffix not in (".png", ".rrd") and b"PRIVATE KEY-----" in p.read_bytes()]


def _env(path: Path) -> dict[str, str]:
    out = {}
    for line in path.read_text().splitlines():
        if line.strip() and not line.lstrip().startswith("#"):
            k, _, v = line.partition("=")
            out[k.strip()] = v.strip()
    return out


def _zfusion_argv(cmd: list[str]) -> list[str]:
    assert Path(cmd[0]).name == "zfusion", cmd
    return cmd[1:]


def _acl_identities() -> set[str]:
    acl = json.loads(zenoh.Config.from_file(str(ZENOH / "router-tls-acl.json5")).get_json("access_control"))
    return {cn for subject in acl["subjects"] for cn in subject["cert_common_names"]}


def _check_cli(argv: list[str]) -> None:
    """The command parses; the Zenoh configs it names exist in deploy/zenoh/; a process
    with a certificate uses the one of its own process id, an identity the router knows."""
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as e:
        raise AssertionError(f"zfusion rejects: {shlex.join(argv)}") from e
    for a in argv:
        if a.endswith(".json5"):
            assert (ZENOH / Path(a).name).is_file(), a
    certs = [Path(o.partition("=")[2]).stem for o in args.zenoh_set or [] if "connect_certificate=" in o]
    if certs:
        me = tracker_id(args.sensor) if args.command == "tracker" else args.id
        assert certs == [me] and me in _acl_identities(), (me, certs)


def test_systemd_units_run_commands_the_cli_accepts():
    env = _env(DEPLOY / "systemd" / "zfusion.env")
    units = sorted((DEPLOY / "systemd").glob("*.service"))
    assert {u.name for u in units} == {"zfusion-router.service", "zfusion-sensor@.service", "zfusion-tracker@.service",
                                       "zfusion-fuser.service", "zfusion-record.service"}
    for unit in units:
        text = unit.read_text()
        assert re.search(r"^Restart=", text, re.M) and re.search(r"^KillSignal=SIGINT$", text, re.M), unit.name
        (line,) = re.findall(r"^ExecStart=(.*)$", text.replace("\\\n", " "), re.M)  # continuation lines joined
        line = re.sub(r"\$\{(\w+)\}", lambda m: env[m.group(1)], line).replace("%i", "radar2d")
        cmd = shlex.split(line)
        if Path(cmd[0]).name == "zenohd":
            assert (ZENOH / Path(cmd[cmd.index("-c") + 1]).name).is_file(), unit.name
            continue
        _check_cli(_zfusion_argv(cmd))


def test_compose_file_parses_and_runs_commands_the_cli_accepts():
    import yaml

    doc = yaml.safe_load((DEPLOY / "compose.yaml").read_text())
    services = doc["services"]
    assert services["router"]["image"].startswith("eclipse/zenoh")
    zf = {n: s for n, s in services.items() if n != "router"}
    assert {"fuser", "recorder"} <= set(zf) and any(n.startswith("sensor-") for n in zf)
    for name, svc in zf.items():
        _check_cli(svc["command"])
        assert "router" in svc.get("depends_on", []), name
    for svc in services.values():
        for vol in svc.get("volumes", []):
            src = vol.split(":")[0]
            if src.startswith("./") and not src.startswith("./certs"):  # certs: made on site, never committed
                assert (DEPLOY / src).exists(), (svc, vol)

