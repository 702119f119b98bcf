"""Security at the router (deploy/zenoh/router-tls-acl.json5): mutual TLS, and access
control by certificate common name with default deny.

Certificates are made here, into a temporary directory, by the site's own script
(deploy/make-certs.sh, openssl); none is committed. The router, the fuser and the
sensors are real ``zfusion`` processes run with the committed configs, only the
certificate paths and endpoints set on the command line, as docs/deploy.md says."""

from __future__ import annotations

import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh

from fusion.types import Estimate
from schemas import KeySpace, decode, encode, encode_estimate, tracker_id
from services.launcher import free_port
from services.supervisor import Children
from services.node import ZenohOptions
from sensors_sim import load_scenario

from _multihost import DEPLOY, ROUTER_HOST, ZENOH, Watcher, site, wait_listening
from _runs import in_process, same_series

pytestmark = pytest.mark.slow

TLS = "transport/link/tls"
IDENTITIES = ("router", "radar2d", "angle", "trk-radar2d", "trk-angle", "fuser", "recorder", "mallory")
FORGED = 10**6  # the seq that marks a forged message


@pytest.fixture(scope="module")
def certs(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("certs")
    subprocess.run([str(DEPLOY / "make-certs.sh"), str(d), *IDENTITIES], check=True, timeout=60)
    return d


def identity(certs: Path, name: str, side: str = "connect", ca: Path | None = None) -> list[str]:
    """``--zenoh-set`` values: trust the CA in ``ca`` (default: ``certs``), and show the
    certificate of ``name`` when connecting (clients) or listening (the router)."""
    return [f"{TLS}/root_ca_certificate={ca or certs}/ca.pem", f"{TLS}/{side}_private_key={certs}/{name}.key",
            f"{TLS}/{side}_certificate={certs}/{name}.pem"]


@pytest.fixture(scope="module")
def router(certs):
    """``zfusion router`` with the production config; yields its TLS endpoint."""
    port = free_port()
    children = Children()
    files = ZenohOptions(config_file=str(ZENOH / "router-tls-acl.json5"), overrides=identity(certs, "router", "listen"))
    children.start("router", ["router", *files.to_args(), "--listen", f"tls/{ROUTER_HOST}:{port}"])
    try:
        wait_listening(ROUTER_HOST, port, children.procs["router"])
        yield f"tls/{ROUTER_HOST}:{port}"
    finally:
        children.stop_all()
    assert children.procs["router"].returncode == 0


def client(endpoint: str, overrides: list[str]) -> ZenohOptions:
    return ZenohOptions(config_file=str(ZENOH / "client-tls.json5"), connect=[endpoint], overrides=overrides)


def process_args(endpoint: str, certs: Path, name: str, deployment: str) -> list[str]:
    o = client(endpoint, identity(certs, name))
    return [*o.to_args(), "--deployment", deployment]


def matched(pub: zenoh.Publisher, timeout: float = 30.0) -> bool:
    """Whether the publisher's session learns of a subscriber to its key: only then does a
    Zenoh client actually send its samples to the router."""
    deadline = time.monotonic() + timeout
    while not pub.matching_status.matching and time.monotonic() < deadline:
        time.sleep(0.05)
    return pub.matching_status.matching


@pytest.mark.parametrize("topology,method", [("centralised", "SS"), ("feedback", "PHHNV")])
def test_only_authorised_identities_reach_the_fuser(certs, router, deployment, topology, method):
    scenario = load_scenario("patent-3d")
    keys = KeySpace(deployment)
    ref = in_process("patent-3d", method)
    plan = site(scenario, method, topology, watcher="recorder")
    consumers = [n for n in plan if n not in scenario.sensors]  # fuser, trackers
    # The test watches everything under the deployment with the recorder's certificate.
    watcher = Watcher(client(router, identity(certs, "recorder")).to_config(), keys)
    intruders = {n: zenoh.open(client(router, identity(certs, n)).to_config()) for n in ("angle", "mallory")}
    children = Children()
    try:
        for name, argv in plan.items():  # each with its own certificate (CN = process id)
            children.start(name, [*argv, *process_args(router, certs, name, deployment)])
        for name in consumers:
            assert watcher.wait_alive(name, 30.0), f"{name} (certificate CN={name}) did not come up"

        # Attacks, while the consumers listen and before the sensors start: forged
        # measurements and tracks, valid on the wire and marked by their seq, from the
        # angle sensor's identity (authorised, but for its own keys only) and from a
        # certificate of the site's CA whose common name no rule names.
        forged_meas = encode("range_az", "radar2d", FORGED, 0.5, sensor="radar2d", site=[0.0, 0.0, 0.0], az=0.5,
                             std_az=0.01, range=1e4, std_range=20.0)
        forged_track = encode_estimate(Estimate(t=0.5, x=np.zeros(6), P=np.eye(6), method=method), "fuser", FORGED)
        forgeries = {keys.meas("radar2d"): forged_meas, keys.fused("fuser"): forged_track}
        if topology != "centralised":
            forgeries |= {keys.local("trk-radar2d"): forged_track, keys.feedback("trk-angle"): forged_track}
        angle, mallory = intruders["angle"], intruders["mallory"]
        for key, payload in forgeries.items():
            pub = angle.declare_publisher(key)
            # The angle identity hears who subscribes, so its client really sends the
            # forged samples: what stops them is the router.
            assert matched(pub), key
            mallory_pub = mallory.declare_publisher(key)
            for _ in range(3):
                pub.put(payload)
                mallory_pub.put(payload)
        mallory.put(keys.meas("mallory"), forged_meas)
        # Unknown to the access control, mallory is told nothing, not even who listens.
        assert not matched(mallory.declare_publisher(keys.fused("fuser")), timeout=0.5)

        watcher.announce("recorder")  # the sensors wait for it: the scenario starts now
        for name in plan:
            assert children.wait(name, 60.0) == 0, name
        watcher.wait_fused(ref["n_updates"])
        seen = [(k, decode(d)) for k, d in watcher.samples]
        # (b) nothing forged went through: on meas/<s> and local/<t> only s and t speak,
        # on fused and feedback/ only the fuser...
        owner = {"meas": None, "local": None, "fused": "fuser", "feedback": "fuser"}
        for k, m in seen:
            family, ident = keys.family_and_id(k)
            if family in owner:
                assert m.seq != FORGED and m.src == (owner[family] or ident), (k, m.src)
        assert {k for k, _ in seen if keys.family_and_id(k)[0] == "meas"} == {keys.meas(s) for s in scenario.sensors}
        # ... and no process rejected anything, because nothing foreign arrived.
        done = {m.src: m.body for k, m in seen if keys.family_and_id(k)[0] == "status" and m.body["state"] == "done"}
        fused_sources = [tracker_id(s) for s in scenario.sensors] if topology != "centralised" else scenario.sensors
        assert "fuser" in done and set(done["fuser"]["sources"]) == set(fused_sources)
        assert all(body["counters"]["rejected"] == 0 for body in done.values()), done
        # (a) the authorised processes' data reached the fuser, whose output is exactly that
        # of the in-process evaluation.
        same_series(watcher.summary(scenario), ref)
    finally:
        for session in intruders.values():
            session.close()
        watcher.close()
        children.stop_all()


@pytest.mark.parametrize("who", ["no certificate", "certificate of another CA", "plain tcp"])
def test_no_valid_certificate_no_connection(certs, router, tmp_path, who):
    """(d) Whatever a client claims, without a certificate from the site's CA it cannot
    even open a session (the router requires mutual TLS and speaks nothing else)."""
    if who == "no certificate":
        o = client(router, [f"{TLS}/root_ca_certificate={certs}/ca.pem", f"{TLS}/connect_private_key=null",
                            f"{TLS}/connect_certificate=null"])
    elif who == "certificate of another CA":
        subprocess.run([str(DEPLOY / "make-certs.sh"), str(tmp_path), "fuser"], check=True, timeout=60)
        o = client(router, identity(tmp_path, "fuser", ca=certs))
    else:
        o = ZenohOptions(mode="client", connect=[router.replace("tls/", "tcp/")])
    with pytest.raises(zenoh.ZError):
        zenoh.open(o.to_config()).close()
    # A certificate of the site's CA does get in (the refusal above is about the certificate).
    zenoh.open(client(router, identity(certs, "mallory")).to_config()).close()
