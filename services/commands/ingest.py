"""``zfusion ingest krakensdr|adsb|asterix|jsonl``: a gateway for real sensors (:mod:`services.ingest.process`).

A new gateway registers its sub-parser in :func:`register` and its loop in
:func:`services.ingest.process.main`.
"""

from __future__ import annotations

import argparse

from fusion.lazy import lazy

from . import options

process = lazy("services.ingest.process")
values = lazy("services.commands.values")


def register(sub) -> None:
    p = sub.add_parser("ingest", help="a gateway for real sensors: KrakenSDR, ADS-B, JSON lines, ASTERIX")
    gw = p.add_subparsers(dest="gateway", required=True, metavar="GATEWAY")

    k = gw.add_parser("krakensdr", help="a KrakenSDR DF station (Kraken App CSV, doa.xml, Kraken Pro POSTs)")
    src = k.add_mutually_exclusive_group(required=True)
    src.add_argument("--url", help="poll the station's web server, e.g. http://HOST:8081")
    src.add_argument("--listen", metavar="HOST:PORT", help="take the station's POSTs, e.g. 127.0.0.1:8042")
    k.add_argument("--format", choices=("auto", "csv", "xml", "json"), default="auto",
                   help="auto: told by the content (default); csv: /DOA_value.html; xml: /doa.xml; json: POSTs")
    k.add_argument("--poll-s", type=float, default=1.0, help="seconds between polls (default %(default)s)")
    k.add_argument("--timeout-s", type=float, default=2.0, help="HTTP timeout (default %(default)s s)")
    k.add_argument("--doa", choices=("auto", "cw", "ccw"), default="auto",
                   help="how the DoA is counted from the array: auto (CSV cw as 360-θ, XML/JSON ccw θ; default)")
    k.add_argument("--heading", default="message",
                   help="message: add the message's heading (default); none: the DoA is from true north; "
                        "or a fixed heading in degrees")
    k.add_argument("--vfo", type=float, action="append", metavar="MHZ",
                   help="a VFO channel to publish (repeatable: channel k as <id>-<k>); default: VFO 0")
    k.add_argument("--vfo-tol-khz", type=float, default=12.5, help="channel match tolerance (default %(default)s)")
    k.add_argument("--min-conf", type=float, default=0.0, help="skip readings of lower confidence (default 0)")
    k.add_argument("--station", help="only readings of this station id (default: any)")
    _common(k)

    a = gw.add_parser("asterix", help="ASTERIX radar plots and scan timing (CAT048, CAT034) over UDP or from a pcap "
                                      "(docs/asterix.md)")
    src = a.add_mutually_exclusive_group(required=True)
    src.add_argument("--udp", metavar="[GROUP@]HOST:PORT",
                     help="receive datagrams here (GROUP: an IPv4 multicast group joined on HOST's interface)")
    src.add_argument("--pcap", metavar="FILE", help="replay the UDP datagrams of a pcap capture (its times are the clock)")
    a.add_argument("--speed", default="1", help="pcap replay speed: a factor, or max (default %(default)s)")
    a.add_argument("--sector-lag", type=int, default=1,
                   help="a CAT034 crossing promises the plots older than this many crossings back (default "
                        "%(default)s: radars send a sector's plots after its crossing)")
    a.add_argument("--scenario-run", metavar="SENDERS",
                   help="with --udp, a scenario run's gateway (zfusion run --asterix-in): the times of day are "
                        "scenario seconds (no clock checks, no heartbeats), and once each of these processes "
                        "(comma-separated) has reported done, their streams end, and so does this gateway")
    _common(a, "this gateway's process id (its radars: the site file's sensors with sac_sic)")

    b = gw.add_parser("adsb", help="an ADS-B receiver: readsb/dump1090-fa/tar1090 aircraft.json, or its BaseStation "
                                   "(SBS-1) feed (docs/ingest.md)")
    src = b.add_mutually_exclusive_group(required=True)
    src.add_argument("--url", help="poll the receiver's aircraft.json, e.g. http://HOST/tar1090/data/aircraft.json")
    src.add_argument("--sbs", metavar="HOST:PORT", help="read its BaseStation feed, e.g. 127.0.0.1:30003")
    b.add_argument("--poll-s", type=float, default=1.0,
                   help="seconds between polls, and the first reconnection wait (default %(default)s)")
    b.add_argument("--timeout-s", type=float, default=2.0, help="HTTP or connect timeout (default %(default)s s)")
    b.add_argument("--sources", default="adsb,mlat,tisb,adsc",
                   help="which positions to publish: adsb, mlat, tisb, adsc, other (default %(default)s)")
    b.add_argument("--sbs-timezone", default="auto",
                   help="SBS times: auto (the receiver's offset from this clock; default), UTC (readsb), or an "
                        "IANA zone (dump1090-fa writes local time)")
    b.add_argument("--sbs-mlat", action="store_true", help="the SBS feed carries multilateration results")
    _common(b, "the receiver's id (a [sensors.<id>] of kind adsb in the site file)")

    j = gw.add_parser("jsonl", help="one JSON measurement per line (docs/ingest.md)")
    j.add_argument("--input", default="-", help="-, a file, udp://HOST:PORT or tcp://HOST:PORT (default: stdin); a "
                                                "file (or stdin from one) replays on its own clock: no heartbeats, "
                                                "ages measured from its newest reading")
    _common(j)


def _common(q: argparse.ArgumentParser, id_help: str = "the sensor id (a [sensors.<id>] of the site file)") -> None:
    """What every gateway takes: its id, the site, the clock checks, the fabric."""
    q.add_argument("--id", required=True, help=id_help)
    q.add_argument("--site", required=True, metavar="FILE", help="the site file (or any scenario file)")
    q.add_argument("--max-skew", type=float, default=5.0,
                   help="seconds a time stamp may be ahead of this clock (default %(default)s)")
    q.add_argument("--max-age", type=float, default=60.0,
                   help="seconds a time stamp may be behind this clock (default %(default)s)")
    q.add_argument("--watermark-lag", type=float, default=2.0,
                   help="heartbeat watermarks promise everything older than now minus this (default "
                        "%(default)s s); a reading that arrives later is dropped as late; 0: no heartbeats "
                        "(a replay of old data)")
    q.add_argument("--wait-for", type=options.ids, default=[], metavar="IDS",
                   help="comma-separated processes to wait for before the first reading is published (a "
                        "replay into a fuser just started: what goes out before it is heard is lost to it)")
    options.fabric(q)
    q.set_defaults(main=run)


def run(args) -> int:
    return process.main(args, values.keys(args), values.zopts(args))
