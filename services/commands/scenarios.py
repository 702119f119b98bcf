"""``zfusion scenarios``: the built-in scenarios, one line each."""

from __future__ import annotations

from fusion.lazy import lazy
sensors_sim = lazy("sensors_sim")


def register(sub) -> None:
    p = sub.add_parser("scenarios", help="list the built-in scenarios")
    p.set_defaults(main=run)


def run(args) -> int:
    rows = sensors_sim.list_scenarios()
    width = max(len(n) for n, _ in rows)
    for name, line in rows:
        print(f"{name:<{width}}  {line}")
    return 0
