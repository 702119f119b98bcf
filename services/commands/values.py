"""What the shared options mean once a command runs: the key space, the Zenoh options,
a live session's options and the scenario's (or site's) defaults.

Loaded by the commands when they run (:func:`fusion.lazy.lazy`), never to build the
parser: it imports the wire schemas (numpy) and Zenoh.
"""

from __future__ import annotations

from schemas import KeySpace

from ..live import LiveOptions
from ..node import ZenohOptions
from ..scenario import load, load_site


def keys(args) -> KeySpace:
    return KeySpace(args.deployment)


def zopts(args) -> ZenohOptions:
    return ZenohOptions(connect=args.connect or [], config_file=args.zenoh_config,
                        mode=getattr(args, "zenoh_mode", None), overrides=getattr(args, "zenoh_set", None) or [])


def live(args) -> LiveOptions | None:
    """The live options of a process started with ``--site`` (None for ``--scenario``)."""
    if getattr(args, "site", None) is None:
        return None
    return LiveOptions(max_skew=args.max_skew, max_delay=getattr(args, "max_delay", 1.0),
                       oosm_window=getattr(args, "oosm_window", 10.0))


def given(args):
    """The site (``--site``) or the scenario (``--scenario``) a command names, loaded."""
    return load_site(args.site) if getattr(args, "site", None) is not None else load(args.scenario)


def defaults(args) -> dict:
    """The ``[defaults]`` of ``--scenario`` or ``--site``."""
    return given(args).defaults
