"""What a command asks for, checked against its scenario before anything starts: the
scenario with ``--seed`` and ``--duration-s``, the method and its topology, and the
``[tracker]`` table with the command line's overrides. Each refusal is a
:class:`~services.errors.UserError` (one line, exit 2), raised here rather than by a
child process seconds later.
"""

from __future__ import annotations

from fusion.methods import METHODS, make_method, method_config, topology_default
from fusion.mtt import AssociationConfig
from sensors_sim.spec import DF_KINDS

from .errors import UserError
from .evaluation import method_misfit
from .scenario import load
from .scoring import many_targets


def scenario_of(args):
    """``--scenario`` with ``--seed`` and ``--duration-s`` applied."""
    return load(args.scenario, args.seed, getattr(args, "duration_s", None))


def check_methods(scenario, methods: list[str], overrides: dict) -> None:
    """Every method must be one the scenario's sensors can feed, and accept the scenario's
    ``[tracker]`` table with the overrides (an unknown key, a bad value)."""
    for m in methods:
        misfit = method_misfit(scenario, m)
        if misfit:
            raise UserError(misfit)
        try:
            make_method(m, method_config(scenario.tracker, m, overrides))
        except ValueError as e:
            raise UserError(str(e)) from None
        if many_targets(scenario) and AssociationConfig.split(method_config(scenario.tracker, m, overrides))[0] is None:
            # a single-target method would follow one of them and be scored against all
            raise UserError(f"scenario {scenario.name} has {len(scenario.targets) or 'changing'} targets but no "
                            f"association: {m} alone follows one target; add association = \"gnn\" to its "
                            f"[tracker] table, or --set association=gnn")


def topology_of(method: str) -> str:
    return METHODS[method].topology if method in METHODS else "centralised"  # an unknown one fails at make_method


def resolve_topology(scenario, topology: str | None, method: str | None) -> tuple[str, str]:
    """Topology and method from the command line and the scenario's defaults; they must
    agree (``regional``: a centralised method, in a scenario with ``[regions]``)."""
    default = scenario.defaults.get("method")
    if topology == "regional":
        method = method or default
        if not scenario.regions:
            raise UserError(f"--topology regional needs [regions.<name>] tables; {scenario.name} has none "
                            f"(docs/regional.md)")
        if not method or topology_of(method) != "centralised":
            raise UserError(f"--topology regional runs a centralised many-target method as regional fusers; "
                            f"give --method (not {method})")
        clash = set(scenario.regions) & (set(scenario.process_ids()) | {"fuser", "recorder", "router"})
        if clash:
            raise UserError(f"--topology regional: region {sorted(clash)[0]!r} has the id of another process; "
                            f"rename the region")
        return topology, method
    if method is None and topology is not None and (default is None or topology_of(default) != topology):
        if topology == "centralised":
            raise UserError(f"scenario {scenario.name} names no centralised method; give --method")
        df = all(scenario.kind_of(s) in DF_KINDS for s in scenario.sensors)
        method = topology_default(topology, "df" if df else "3d")
        if method is None:
            raise UserError(f"no DF method runs in the {topology!r} topology (docs/design.md, Topologies)")
    method = method or default
    if not method:
        raise UserError("no --method given and the scenario names no default method")
    topology = topology or topology_of(method)
    if topology_of(method) != topology:
        raise UserError(f"method {method} runs in the {topology_of(method)!r} topology, not {topology!r}")
    return topology, method
