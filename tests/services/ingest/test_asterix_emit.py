"""The ASTERIX emitter (services/ingest/asterix_emit.py), in process: an emulated radar's
sectors as CAT048 plots and CAT034 crossings, an ADS-B station's positions as CAT021,
read back by the gateway core (services/ingest/asterix.py). What comes back is the
emulated measurement on the items' grid; the crossings promise only plots already sent;
a sensor that cannot send ASTERIX is refused, and ``zfusion sensor --asterix``'s mistakes
are one line and exit 2."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from schemas import asterix as ax
from sensors_sim import load_scenario
from sensors_sim.emulators import sensor_batches
from schemas import KeySpace, decode
from services.ingest.asterix import (
    AsterixFeed, AsterixIngest, ScanMark, StationReport, pcap_datagrams, pcap_file, radars, with_sac_sic)
from services.ingest.asterix_emit import RadarEmitter, StationEmitter, datagrams, emitter
from services.ingest.gateway import Gateway, Reading, local_frame, sensor_sites
from services.node import RejectLog
from services.plan import ASTERIX_ID, Asterix, Live, RunPlan

SCENARIO = Path(__file__).parents[2] / "data" / "asterix-region.toml"
AIR_PICTURE = Path(__file__).parents[3] / "sensors_sim" / "scenarios" / "air-picture.toml"
NM, FT = 1852.0, 0.3048


@pytest.fixture(scope="module")
def sc():
    return load_scenario(SCENARIO)


@pytest.mark.parametrize("sid", ["radar2d", "radar3d"])
def test_a_rotating_radar_reads_back_as_its_measurements_and_never_late(sc, sid):
    frame = local_frame(sc)
    feed = AsterixFeed(radars(sc, frame))  # sector_lag 1, the gateway's default
    em = emitter(sc, sid)
    assert isinstance(em, RadarEmitter) and em.sectors == sc.sensor(sid).sectors
    promised, readings, marks, sent = -math.inf, 0, 0, 0
    for b in sensor_batches(sc, sid):
        ms = [ev.measurement for ev in b.events if ev.measurement is not None]
        sent += len(ms)
        got = [ev for d in datagrams(em.records(b.t1, b.events, lambda t: t)) for ev in feed.receive(d, b.t1)]
        plots = [ev for ev in got if isinstance(ev, Reading)]
        assert readings + len(plots) + em.unencodable == sent
        for ev in got:
            if isinstance(ev, ScanMark):
                assert ev.t >= promised
                promised, marks = ev.t, marks + 1
            else:
                assert ev.t > promised  # sent after its crossing, promised one crossing later
        by_seq = {round(m.t * 128): m for m in ms}  # each plot's time is its own here
        for r in plots:
            m = by_seq[round(r.t * 128)]
            assert r.sensor == sid and r.kind == m.kind
            assert abs(r.t - m.t) <= 1 / 256 + 1e-9
            assert abs(math.remainder(r.z[0] - m.z[0], 2 * math.pi)) <= math.pi / 65536 + 1e-9 + (
                0.0 if m.kind == "range_az" else 12.5 * FT / m.z[-1])
            assert abs(r.z[-1] - m.z[-1]) <= NM / 512 + 1e-9
        readings += len(plots)
    for t, recs in em.end(lambda t: t):
        for d in datagrams(recs):
            promised = max([promised] + [ev.t for ev in feed.receive(d, t) if isinstance(ev, ScanMark)])
    assert promised >= sc.duration - 1e-9  # the trailing crossings promise the last plots
    turns = (sc.duration - sc.sensor(sid).start) / sc.sensor(sid).period
    assert marks >= turns * sc.sensor(sid).sectors - 2 and readings >= 0.9 * sent > 50
    assert em.unencodable <= 2  # 3D clutter above I048/110's 204,800 ft


@pytest.fixture(scope="module")
def snapshot(tmp_path_factory):
    """air-picture with SAC/SIC 0/1 and 0/2 for its two snapshot 2D radars."""
    text, assigned = with_sac_sic(AIR_PICTURE.read_text(), load_scenario(AIR_PICTURE))
    assert assigned == {"radar1": (0, 1), "radar2": (0, 2)}  # the angle sensors have no ASTERIX category
    p = tmp_path_factory.mktemp("snapshot") / "air-picture.toml"
    p.write_text(text)
    return load_scenario(p)


def test_a_snapshot_radar_sends_a_north_marker_per_scan_and_the_direct_streams_watermarks(snapshot):
    sc = snapshot
    frame = local_frame(sc)
    log = RejectLog("t")
    gw = Gateway(sensor_sites(sc, ["radar1", "radar2"]), frame, KeySpace("t"), log, lag=0.0)
    ingest = AsterixIngest(AsterixFeed(radars(sc, frame), sector_lag=1), gw, log)  # a snapshot radar: no lag
    em = emitter(sc, "radar1")
    assert isinstance(em, RadarEmitter) and em.sectors == 0
    batches = list(sensor_batches(sc, "radar1"))
    promised, marks, readings = -math.inf, [], 0
    for b in batches:
        records = em.records(b.t1, b.events, lambda t: t)
        marker, *plots = records  # the scan's north marker first, then its plots
        assert (marker.category, marker.message_type, marker.tod, marker.rotation_period) == (
            34, ax.NORTH_MARKER, b.t1, 1.0)
        assert [r.category for r in plots] == [48] * sum(ev.measurement is not None for ev in b.events)
        for d in datagrams(records):
            for _, data in ingest.receive(d, b.t1 + 0.5):
                m = decode(data)
                if m.kind == "watermark":
                    marks.append(m.t)
                    promised = m.t
                else:
                    assert m.t > promised  # sent after its scan's marker: never behind a promise
                    readings += 1
    for t, recs in em.end(lambda t: t):
        assert t == batches[-1].t1 + 1.0 and [r.message_type for r in recs] == [ax.NORTH_MARKER]
        marks += [decode(data).t for d in datagrams(recs) for _, data in ingest.receive(d, t)]
    # the direct stream's watermarks (services/source.py): after scan k, just before scan k + 1
    direct = [math.nextafter(nxt.t0, -math.inf) for nxt in batches[1:]]
    assert marks == [math.nextafter(batches[0].t1, -math.inf), *direct,
                     math.nextafter(batches[-1].t1 + 1.0, -math.inf)]
    assert marks[-1] >= sc.duration and not log.by_cause and readings > 0.9 * len(batches) * 12


def test_an_adsb_station_sends_cat021(sc):
    frame = local_frame(sc)
    em = emitter(sc, "gs")
    assert isinstance(em, StationEmitter)
    # 30 m per axis: NACp 8 (0.05 NM, σ 37.9 m) is nearer than NACp 9 (30 m, σ 13.3 m)
    assert (em.nacp, em.gva) == (8, 1)
    feed = AsterixFeed({})
    n = 0
    for b in sensor_batches(sc, "gs"):
        evs = [ev for ev in b.events if ev.measurement is not None]
        got = [r for d in datagrams(em.records(b.t1, b.events, lambda t: 3600.0 + t)) for r in feed.receive(d, 7200.0)]
        assert len(got) == len(evs)
        for ev, r in zip(evs, got):
            assert isinstance(r, StationReport) and r.sac_sic == (30, 4)
            rep = r.report
            assert rep.t == pytest.approx(3600.0 + ev.t, abs=1 / 256)
            enu = frame.to_enu(rep.lat_deg, rep.lon_deg, rep.alt_m)
            np.testing.assert_allclose(enu, ev.measurement.z, atol=3.2 * FT + 0.01)  # 6.25 ft, 180°/2³⁰
            assert rep.nac_p == 8 and rep.alt_ref == "geometric"
            assert int(rep.address, 16) == emitter(sc, "gs").records(
                b.t1, [ev], lambda t: t)[0].address  # one address per target
        n += len(got)
    assert n > 60


def test_what_cannot_send_asterix_is_refused(sc, tmp_path):
    no = tmp_path / "no.toml"
    no.write_text(SCENARIO.read_text().replace("sac_sic = [25, 1]\n", ""))
    with pytest.raises(ValueError, match="no sac_sic"):
        emitter(load_scenario(no), "radar2d")
    angle = tmp_path / "angle.toml"
    angle.write_text(SCENARIO.read_text().replace('kind = "radar2d"', 'kind = "angle"\nstd_el_deg = 0.1').replace(
        "std_range_m = 40.0\n", "").replace("rotation_period_s = 4.0\nsectors = 16\n", "period_s = 1.0\n"))
    with pytest.raises(ValueError, match="range_az or az_el_range"):
        emitter(load_scenario(angle), "radar2d")


def test_a_capture_of_the_emitted_datagrams_reads_back(sc):
    em = emitter(sc, "radar2d")
    packets = [(1e9 + b.t1, d) for b in sensor_batches(sc, "radar2d")
               for d in datagrams(em.records(b.t1, b.events, lambda t: t))]
    assert list(pcap_datagrams(pcap_file(packets))) == [(pytest.approx(t, abs=1e-6), d) for t, d in packets]
    # the crossing out of the last sector of the first turn is north: the marker goes with it
    (north,) = [d for b in sensor_batches(sc, "radar2d") if b.t1 == 4.0
                for d in datagrams(emitter(sc, "radar2d").records(b.t1, b.events, lambda t: t))]
    crossing, marker = ax.decode(north)[:2]
    assert (crossing.message_type, crossing.sector, crossing.tod) == (ax.SECTOR_CROSSING, 0.0, 4.0)
    assert (marker.message_type, marker.rotation_period, marker.tod) == (ax.NORTH_MARKER, 4.0, 4.0)


def test_sensor_asterix_mistakes_are_one_line_and_exit_2(tmp_path):
    no = tmp_path / "no.toml"
    no.write_text(SCENARIO.read_text().replace("sac_sic = [25, 1]\n", ""))
    for args, says in ((["--scenario", str(SCENARIO), "--id", "radar2d", "--live", "--asterix", "udp://nowhere"],
                        "HOST:PORT"),
                       (["--scenario", str(SCENARIO), "--id", "truth", "--live", "--asterix", "udp://127.0.0.1:9"],
                        "not a sensor"),
                       (["--scenario", str(no), "--id", "radar2d", "--live", "--asterix", "udp://127.0.0.1:9"],
                        "no sac_sic"),
                       (["--scenario", str(SCENARIO), "--id", "radar2d", "--asterix-pcap",
                         str(tmp_path / "no" / "such" / "dir.pcap")], "--asterix-pcap")):
        p = subprocess.run([sys.executable, "-m", "services.cli", "sensor", *args], capture_output=True, text=True,
                           timeout=60)
        assert p.returncode == 2, (args, p.stderr)
        assert says in p.stderr and "Traceback" not in p.stderr and len(p.stderr.strip().splitlines()) == 1


def test_a_plan_routes_the_radars_and_stations_through_one_gateway(snapshot, tmp_path):
    """``zfusion plan --asterix-in``: air-picture's radars send ASTERIX to the gateway on
    the given port, in the site file with their SAC/SIC; its angle sensors publish on
    Zenoh as ever; the gateway is up before the radars start, and waited for."""
    p = subprocess.run([sys.executable, "-m", "services.cli", "plan", "--scenario", "air-picture", "--asterix-in",
                        "127.0.0.1:8611", "--rrd", str(tmp_path / "site.rrd")], capture_output=True, text=True,
                       timeout=60)
    assert p.returncode == 0, p.stderr
    site = tmp_path / "site.asterix.toml"
    assert {sid: s.sac_sic for sid, s in load_scenario(site).sensors.items()} == {
        sid: s.sac_sic for sid, s in snapshot.sensors.items()}
    lines = [ln for ln in p.stdout.splitlines() if not ln.startswith("#")]
    (gw,) = [ln for ln in lines if " ingest asterix " in ln]
    assert f"--id {ASTERIX_ID} --site {site} --udp 127.0.0.1:8611 --scenario-run radar1,radar2" in gw
    assert lines.index(gw) < min(i for i, ln in enumerate(lines) if " sensor " in ln)
    for sid in ("radar1", "radar2"):
        (ln,) = [ln for ln in lines if f" --id {sid} " in ln]
        assert f"--scenario {site} " in ln and "--asterix udp://127.0.0.1:8611" in ln
        assert f"--wait-for fuser,recorder,{ASTERIX_ID} " in ln
    for sid in ("angle1", "angle2"):
        (ln,) = [ln for ln in lines if f" --id {sid} " in ln]
        assert "--scenario air-picture " in ln and "--asterix" not in ln
    # a scenario run's gateway reads scenario seconds and ends when its senders are done,
    # and the recorder waits for it; a live one reads UTC, and runs until stopped
    route = Asterix(str(site), "127.0.0.1:8611", ("radar1", "radar2"))
    run = RunPlan.build("air-picture", snapshot, "centralised", "SS", fabric=[], asterix=route)
    gw = run[ASTERIX_ID]
    assert gw.role == "gateway" and gw.argv[gw.argv.index("--scenario-run") + 1] == "radar1,radar2"
    # it publishes once the takers of its sensors' data have announced themselves (before: lost to them)
    assert gw.argv[gw.argv.index("--wait-for") + 1] == "fuser,recorder" and gw.waits_for == ("fuser", "recorder")
    assert ASTERIX_ID in run["recorder"].argv[run["recorder"].argv.index("--expect") + 1].split(",")
    live = RunPlan.build("air-picture", snapshot, "centralised", "SS", fabric=[], live=Live(), asterix=route)
    assert "--scenario-run" not in live[ASTERIX_ID].argv
    assert ASTERIX_ID not in live["recorder"].argv[live["recorder"].argv.index("--expect") + 1].split(",")
    assert "--live" in live["radar1"].argv and "--live" not in run["radar1"].argv


def test_run_asterix_in_mistakes_are_one_line_and_exit_2(tmp_path):
    for args, says in ((["--scenario", "df-multi", "--asterix-in", "--live"], "no radar"),
                       (["--scenario", "df-multi", "--asterix-in"], "no radar")):
        p = subprocess.run([sys.executable, "-m", "services.cli", "run", *args, "--rrd", str(tmp_path / "r.rrd")],
                           capture_output=True, text=True, timeout=60)
        assert p.returncode == 2, (args, p.stderr)
        assert says in p.stderr and "Traceback" not in p.stderr and len(p.stderr.strip().splitlines()) == 1
