"""The topologies a method runs in: where its estimation runs and what flows between
the local nodes beside the sensors and the centre.

``centralised``: the sensors' measurements go to the centre, which runs the method.
``distributed``: a local tracker per sensor sends its track up; the centre fuses them.
``feedback``: as ``distributed``, and the fused track is fed back as every local
tracker's next prior. ``two-stage``: the local trackers only predict (from the fed-back
fused track) and send the prediction with their measurement up; the centre fuses the
predictions, updates that with each measurement, and fuses those updates.

A split topology's :class:`Scheme` says this as a value, which the nodes and centre of
:mod:`fusion.network` read. A leaf module (no imports from the package), so a scenario
loader can check a topology's name, and the command line offer the topologies and the
centre's fusion rules, and a ``--set`` key (:data:`TRACKER_KEYS`), without loading the
estimation methods; each method's topology is its registry record's (:mod:`fusion.methods`).
"""

from __future__ import annotations

from dataclasses import dataclass

TOPOLOGIES = ("centralised", "distributed", "feedback", "two-stage")
# The process layouts a run may take: a method's topology, or ``regional`` — a centralised
# many-target method as regional fusers under a system fuser (fusion.regional).
LAYOUTS = (*TOPOLOGIES, "regional")
# The track-to-track fusion rules of a split topology's centre (fusion.track_fusion), named
# here so that the command line offers them without loading the estimation methods.
FUSION_RULES = ("naive", "bar-shalom-campo", "ci", "info")
# Every method's name and topology, in the registry's order (fusion.methods.METHODS, which
# checks it agrees), so the command line checks a method's name without loading them.
METHOD_TOPOLOGIES = {
    **dict.fromkeys(("EKF", "MEKF1", "MEKF2", "MEKF3", "MEKF4", "MEKF5", "IMM", "TORRIERI"), "centralised"),
    "KF+TR": "distributed", "MKF+TR": "distributed",
    **dict.fromkeys(("RADAR2D", "ANGLE", "RADAR3D", "LCDD", "HNDD", "SS"), "centralised"),
    "HNV": "distributed", "PHHNV": "feedback", "DDHNV": "two-stage",
}
# Every key a [tracker] table (and --set) may give some method: the 3D methods'
# (fusion.patent.TrackerConfig), the DF methods' (fusion.df.methods.DFConfig) and the
# many-target association's (fusion.tracking.config.AssociationConfig), as the registry
# checks, so the command line refuses a misspelt --set key without loading them; whether
# the key is one the scenario's method takes is checked once the scenario is loaded.
TRACKER_KEYS = frozenset((
    "association", "ci_criterion", "confirm_m", "confirm_n", "delete_misses", "ekf_iterations", "existence_birth",
    "existence_confirm", "existence_delete", "filter", "fusion_rule", "gate", "gate_prob", "imm_models", "imm_mu0",
    "imm_p", "imm_q_ca", "imm_q_ct", "imm_q_cv", "imm_q_turn", "imm_sigma2", "imm_sojourn_ca", "imm_sojourn_ct",
    "imm_sojourn_cv", "imm_sojourn_turn", "imm_transition", "imm_turn_rates", "init", "init_acc_std",
    "init_acc_std_up", "init_el", "init_el_std", "init_epochs", "init_range", "init_range_std", "init_vel_std",
    "init_vel_std_up", "ipu_cov", "ipu_max_rel", "jpda_star", "local_max_pos_std", "max_climb", "max_gap_s",
    "max_pos_std", "mekf_handoff", "merge_frames", "motion", "p_detect", "p_survive", "pair_tol", "pair_window_s",
    "process_noise", "q", "q11", "q22", "q_up", "revisit_s", "sigma", "smoother_q", "torrieri_bearings",
    "torrieri_iterations",
))


@dataclass(frozen=True)
class Scheme:
    """What flows between the local trackers of a track-fusion method and its centre.

    Attributes:
        predicts: a node sends its prediction and its measurement up, and the centre
            runs the updates (``two-stage``); otherwise a node sends its own update.
        feeds_back: the centre sends each fused estimate down as every member node's
            next prior (``feedback``, ``two-stage``).
    """

    predicts: bool = False
    feeds_back: bool = False

    def __post_init__(self):
        if self.predicts and not self.feeds_back:
            raise ValueError("a node that only predicts needs the fused estimate fed back")

    @property
    def waits_for_horizon(self) -> bool:
        """A one-target node waits for the centre's horizon before it processes a
        measurement: its prior is the fused estimate the centre has still to send."""
        return self.feeds_back

    @property
    def anchored(self) -> bool:
        """Every local track is re-anchored to its fused track each frame (else it drifts
        along what its sensor does not measure)."""
        return self.feeds_back


SCHEMES = {
    "distributed": Scheme(),
    "feedback": Scheme(feeds_back=True),
    "two-stage": Scheme(predicts=True, feeds_back=True),
}


def scheme_of(topology: str) -> Scheme:
    """The scheme of a split topology."""
    try:
        return SCHEMES[topology]
    except KeyError:
        raise ValueError(f"topology {topology!r} has no local trackers (split: {', '.join(SCHEMES)})") from None
