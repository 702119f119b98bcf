"""The fuser's election (services/leader.py) with real Zenoh sessions on loopback, in
one process: the race of a restarted fuser that leads before it is linked to the
running one happens on purpose (the younger leads alone, then the older member's session
links up), and the election must end with the oldest alone leading, then hand over to the
next oldest when that one's session goes."""

from __future__ import annotations

import threading
import time

import zenoh

from conftest import wait_for
from schemas import KeySpace
from sensors_sim import load_scenario
from services.launcher import free_port
from services.leader import Leadership, Member
from services.node import ZenohOptions
from services.plan import FUSER_ID, STANDBY_ID, RunPlan


class Process:
    """A fuser's part in the election: its own session (listening on a free port, dialing
    ``connect``), a :class:`Leadership` of rank ``born``, and what it said, timed."""

    def __init__(self, deployment: str, born: int, connect: list[str], standby: bool = False, grace: float = 60.0):
        self.session = zenoh.open(ZenohOptions(listen=[f"tcp/127.0.0.1:{free_port()}"], connect=connect).to_config())
        self.events: list[tuple[float, str]] = []
        self.election = Leadership(self.session, KeySpace(deployment), "fuser", standby, grace,
                                   lambda line: self.events.append((time.monotonic(), line)), threading.Event(),
                                   born=born, link_wait=2.0, quiet=0.2)

    def said(self) -> list[str]:
        return [line for _, line in self.events]

    def kill(self) -> None:
        """The session goes (its member token with it), as when the process dies."""
        self.session.close()


def _leading(processes: list[Process]) -> list[int]:
    return [p.election.me.born for p in processes if p.election.leads]


def test_a_younger_leader_yields_to_an_older_member_then_the_next_oldest_takes_over(deployment):
    """A younger fuser linked to a sensor only leads alone (it knows no member). An older
    member's session then starts beside it, dialing the sensor: gossip links the two, the
    younger yields (event, ``yielded`` 1) and the older leads; from then on exactly one
    leads. A third, a standby younger than the oldest, joins and stands by. Killing the
    oldest's session hands over to the next oldest (the standby), never to the youngest.
    Without the yield both the older and the younger lead and the test fails."""
    hub = f"tcp/127.0.0.1:{free_port()}"
    sensor = zenoh.open(ZenohOptions(listen=[hub]).to_config())
    running: list[Process] = []
    try:
        young = Process(deployment, 300, [hub])
        running.append(young)
        assert young.election.leads and not young.election.joins
        assert len(young.said()) == 1 and young.said()[0].startswith("leading: no older member")

        old = Process(deployment, 100, [hub])  # started later, but ranks first (an older start stamp)
        running.append(old)
        wait_for(lambda: _leading(running) == [100], "the younger yields and the older alone leads", timeout=20)
        yielded_at = next(t for t, line in young.events if line.startswith("yielded to 100-"))
        assert young.election.yielded == 1 and young.election.takeovers == 1
        assert old.election.takeovers == 1 and old.election.yielded == 0 and not old.election.joins
        (led_at, led), = old.events  # it leads once its links have settled, not as it meets the younger
        assert led.startswith("leading: no older member"), led
        assert yielded_at - led_at < 1.0, yielded_at - led_at  # the younger yields at once (by hand: 0.2 s before)

        middle = Process(deployment, 200, [hub], standby=True)  # the next oldest, a standby
        running.append(middle)
        assert middle.election.joins and not middle.election.leads
        # every change of leadership after the yield is the standby's start only: one leader throughout
        everyone = sorted(p.election.me for p in running)
        wait_for(lambda: all(p.election.members() == everyone for p in running), "every member knows every other",
                 timeout=20)
        assert _leading(running) == [100]
        assert all(t < yielded_at for t, line in young.events if line.startswith("leading"))

        killed_at = time.monotonic()
        old.kill()
        running.remove(old)
        wait_for(lambda: _leading(running) == [200], "the next oldest takes over", timeout=20)
        took = next(t for t, line in middle.events if line == "the leader is gone: taking over")
        assert took - killed_at < 5.0, took - killed_at
        assert len(young.said()) == 2 and young.election.takeovers == 1  # "leading", "yielded to ..."

        middle.kill()
        running.remove(middle)
        wait_for(lambda: _leading(running) == [300], "the last one leads", timeout=20)
        assert young.election.takeovers == 2 and young.election.yielded == 1
    finally:
        for p in running:
            p.election.undeclare()
            p.kill()
        sensor.close()


def test_ties_are_broken_alike_by_the_session_id():
    """Members order by start stamp, then by Zenoh id; the token's chunk round-trips."""
    a, b, c = Member(5, "a1"), Member(5, "b0"), Member(4, "ff")
    assert sorted([a, b, c]) == [c, a, b]
    assert Member.parse(str(b)) == b and Member.parse("x-1") is None and Member.parse("12") is None


def test_a_standby_alone_leads_after_its_grace_and_not_before(deployment):
    """A standby that meets no member (no link at all) leads only once its grace is over."""
    started = time.monotonic()
    p = Process(deployment, 1, [], standby=True, grace=3.0)  # (its start waits 2 s for a link)
    try:
        assert not p.election.leads and not p.election.joins
        wait_for(lambda: p.election.check() or p.election.leads, "the standby leads", timeout=10)
        assert p.said() == ["no leader within the start grace: leading"]
        assert 3.0 <= p.events[0][0] - started <= 3.0 + 1.0
    finally:
        p.election.undeclare()
        p.kill()


def test_zfusion_run_starts_the_standby_once_its_fuser_is_up():
    """The oldest leads, so ``zfusion run --standby`` starts the standby only once the
    fuser is up (its member token declared): the fuser is the older, and leads. The
    sources do not wait for the standby."""
    plan = RunPlan.build("patent-3d", load_scenario("patent-3d"), "centralised", "SS",
                         fabric=["--connect", "tcp/127.0.0.1:7447"], standby=True)
    assert plan[STANDBY_ID].waits_for == (FUSER_ID,) and plan[FUSER_ID].waits_for == ()
    assert all(STANDBY_ID not in s.waits_for for s in plan if s.id != STANDBY_ID)
