"""The scenario or site a command names: ``--scenario`` with ``--seed`` and
``--duration-s`` applied, or ``--site`` (a live session's site file, or a scenario taken
as its site).

Every process of a run is given the same values by the launcher, so they all draw
consistently. A file that cannot be used is the user's mistake: its
``file:line: field: why`` becomes a :class:`~services.errors.UserError` (one line,
exit 2), in one place.
"""

from __future__ import annotations

import dataclasses

from sensors_sim import ScenarioError, load_scenario
from sensors_sim import load_site as load_site_file

from .errors import UserError


def load(scenario_ref: str, seed: int | None = None, duration: float | None = None):
    """A scenario, with ``--seed`` and ``--duration-s`` (if given) replacing the file's."""
    try:
        scenario = load_scenario(scenario_ref)
    except ScenarioError as e:
        raise UserError(str(e)) from None
    if seed is not None:
        scenario = dataclasses.replace(scenario, seed=int(seed))
    if duration is not None:
        scenario = dataclasses.replace(scenario, duration=float(duration))
    return scenario


def load_site(site_ref: str):
    """A site file, or a scenario as its site (``--site``: a live session)."""
    try:
        return load_site_file(site_ref)
    except ScenarioError as e:
        raise UserError(str(e)) from None


def load_given(args):
    """``--site`` if given (a live session), else ``--scenario`` with its overrides."""
    if getattr(args, "site", None) is not None:
        return load_site(args.site)
    return load(args.scenario, getattr(args, "seed", None), getattr(args, "duration_s", None))
