"""The jamming sweep (``jammed-df-sweep``): the robust DF methods against the outlier
probability and law of a barrage jammer, with the SNR axis and the verdicts.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Sequence

from sensors_sim import load_scenario

from ..evaluation import Variant, evaluate
from .figures import pyplot, save_figure
from .tables import fmt, md_table, ratio, write_report

SWEEP_P = (0.05, 0.1, 0.2, 0.3, 0.5, 0.7, 0.9)
SWEEP_LAWS = ("laplacian", "uniform")
LOO_GATE = 3.0  # σ: the conventional 3-sigma bound on a studentised residual (not tuned)


def snr_db(p: float, sigma1: float, sigma2: float) -> float:
    """The IMM thesis's ``SNR = 10·log10(1/((1−p)σ₁² + pσ₂²))`` (σ in rad)."""
    return 10.0 * math.log10(1.0 / ((1.0 - p) * sigma1**2 + p * sigma2**2))


def sweep_variants(duration: float) -> list[Variant]:
    return [
        Variant("EKF", "EKF"),
        Variant("LOO", "TORRIERI", {"gate": LOO_GATE, "pair_tol": duration + 1.0}),
        Variant("ML", "TORRIERI", {"pair_tol": duration + 1.0}),
        Variant("IMM (symmetric)", "IMM", {"imm_transition": "symmetric"}),
        Variant("IMM (iid)", "IMM", {"imm_transition": "iid"}),
    ]


def build_sweep(runs: int, jobs: int = 1, progress=None, ps: Sequence[float] = SWEEP_P,
                laws: Sequence[str] = SWEEP_LAWS) -> dict:
    base = load_scenario("jammed-df")
    jid = next(iter(base.jammers))
    sigma1 = float(next(iter(base.sensors.values())).std[0])
    sigma2 = base.jammers[jid].outlier_std
    points = []
    for law in laws:
        for p in ps:
            jam = dataclasses.replace(base.jammers[jid], p_outlier=float(p), outlier_law=law)
            sc = dataclasses.replace(base, jammers={jid: jam}, tracker={**base.tracker, "imm_p": float(p)},
                                     name=f"jammed-df (p = {p}, {law})")
            doc = evaluate(sc, sweep_variants(sc.duration), runs, jobs=jobs, progress=progress)
            points.append({"law": law, "p": float(p), "snr_db": snr_db(p, sigma1, sigma2), "doc": doc})
    return {"report": "jammed-df-sweep", "runs": runs, "sigma1": sigma1, "sigma2": sigma2, "gate": LOO_GATE,
            "command": f"python -m services.report jammed-df-sweep --runs {runs}", "points": points}


SWEEP_LABELS = ("EKF", "LOO", "ML", "IMM (symmetric)", "IMM (iid)")


def _sweep_tables(bundle: dict) -> dict[tuple[str, str], str]:
    """Per law: final MSE (m²) and textbook CEP50 (median miss, m), with the bound's."""
    out = {}
    for law in SWEEP_LAWS:
        mse, cep = [], []
        for pt in bundle["points"]:
            if pt["law"] != law:
                continue
            ms, crb = pt["doc"]["methods"], pt["doc"]["crb"]
            bound = crb.get("rmse_pos_final")
            head = [fmt(pt["p"], 2), fmt(pt["snr_db"], 2)]
            mse.append([*head, *(fmt(ms[k]["final"]["mse_pos"], 0) for k in SWEEP_LABELS),
                        fmt(None if bound is None else bound**2, 0)])
            cep.append([*head, *(fmt(ms[k]["cep50"], 1) for k in SWEEP_LABELS), fmt(crb.get("cep50"), 1)])
        if mse:
            out[(law, "mse")] = md_table(["p", "SNR (dB)", *SWEEP_LABELS, "CRB"], mse)
            out[(law, "cep")] = md_table(["p", "SNR (dB)", *SWEEP_LABELS, "CRB"], cep)
    return out


def _sweep_plot(bundle: dict, path: Path) -> str:
    plt = pyplot()
    laws = [law for law in SWEEP_LAWS if any(pt["law"] == law for pt in bundle["points"])]
    fig, axes = plt.subplots(2, len(laws), figsize=(6.0 * len(laws), 8.0), squeeze=False, layout="constrained")
    for j, law in enumerate(laws):
        pts = sorted((pt for pt in bundle["points"] if pt["law"] == law), key=lambda pt: pt["snr_db"])
        x = [pt["snr_db"] for pt in pts]
        b = [pt["doc"]["crb"].get("rmse_pos_final") for pt in pts]
        for i, (key, scale, label) in enumerate((("mse", 1e-6, "final MS position error (km²)"),
                                                 ("cep", 1.0, "CEP50: median miss of the final fixes (m)"))):
            ax = axes[i, j]
            for k in SWEEP_LABELS:
                m = [pt["doc"]["methods"][k] for pt in pts]
                y = [v["final"]["mse_pos"] * scale if key == "mse" else v["cep50"] for v in m]
                ax.plot(x, y, "o-", ms=3, label=k)
            if key == "mse":
                ax.plot(x, [None if v is None else v * v * scale for v in b], "k--", label="CRB (mixture noise)")
            else:
                ax.plot(x, [pt["doc"]["crb"].get("cep50") for pt in pts], "k--", label="CRB's CEP50")
            ax.set_yscale("log")
            ax.set_xlabel("SNR (dB)")
            ax.set_ylabel(label)
            ax.set_title(f"{law} outliers")
            ax.grid(True, which="both", alpha=0.3)
            ax.legend(fontsize=7)
    return save_figure(fig, path)


def _sweep_verdicts(bundle: dict) -> list[str]:
    out = []
    for law in SWEEP_LAWS:
        pts = [pt for pt in bundle["points"] if pt["law"] == law]
        if not pts:
            continue
        for key, what in (("mse", "final MSE"), ("cep", "CEP50")):
            val = (lambda m: m["final"]["mse_pos"]) if key == "mse" else (lambda m: m["cep50"])  # noqa: E731
            wins = {k: 0 for k in SWEEP_LABELS}
            for pt in pts:
                ms = pt["doc"]["methods"]
                wins[min(SWEEP_LABELS, key=lambda k: val(ms[k]))] += 1
            ekf_worst = sum(max(SWEEP_LABELS, key=lambda k: val(pt["doc"]["methods"][k])) == "EKF" for pt in pts)
            imm_beats_ekf = sum(val(pt["doc"]["methods"]["IMM (symmetric)"]) < val(pt["doc"]["methods"]["EKF"])
                                for pt in pts)
            iid = sum(val(pt["doc"]["methods"]["IMM (iid)"]) < val(pt["doc"]["methods"]["IMM (symmetric)"])
                      for pt in pts)
            out.append(
                f"* **{law}, {what}**: lowest at " + ", ".join(f"{k} {v}" for k, v in wins.items() if v)
                + f" of {len(pts)} SNR points; EKF worst at {ekf_worst}/{len(pts)}; IMM (symmetric) better than "
                f"the EKF at {imm_beats_ekf}/{len(pts)}; the i.i.d. transition better than the symmetric one at "
                f"{iid}/{len(pts)}.")
    out.append(
        "* **Reading.** The MSE is dominated by the few runs in which a filter diverges (a handful of fixes "
        "kilometres off), the CEP50 by the typical run: an IMM that is usually fine but occasionally locks on "
        "outliers has a small CEP50 and a huge MSE. The thesis's claim — IMM far better than the EKF under "
        "jamming — is a claim about both; the counts above say at how many SNRs each holds here.")
    for law in SWEEP_LAWS:
        pts = sorted((pt for pt in bundle["points"] if pt["law"] == law), key=lambda pt: pt["p"])
        ratios = [(pt["p"], ratio(pt["doc"]["methods"]["LOO"]["final"]["mse_pos"], pt["doc"]["crb"]["rmse_pos_final"] ** 2))
                  for pt in pts if pt["doc"]["crb"].get("rmse_pos_final")]
        if ratios:
            out.append(f"* **Leave-one-out against the bound, {law}** (final MSE / CRB MSE by p): "
                       + ", ".join(f"{p} → {r:.2f}" for p, r in ratios) + ".")
    return out


def write_sweep_report(bundle: dict, out_dir: Path) -> Path:
    out_dir = Path(out_dir)
    runs = bundle["runs"]
    tables = _sweep_tables(bundle)
    png = _sweep_plot(bundle, out_dir / "jammed-df-sweep" / "mse_vs_snr.png")
    text = [
        "# The IMM thesis's sweep reproduced (`jammed-df`): MS position error against SNR",
        "",
        f"Regenerate: `{bundle['command']}` (writes `jammed-df-sweep.md`, `jammed-df-sweep.json` and "
        f"`jammed-df-sweep/mse_vs_snr.png`). {runs} Monte Carlo runs per point, seed 1, common random numbers "
        "within each point (every method sees the same bearings).",
        "",
        f"Setting (`sensors_sim/scenarios/jammed-df.toml`, varied in code): emitter (15, 15) km, stations (0, 0), "
        f"(10, 0), (20, 0) km, 40 epochs; each bearing is, with probability p, replaced by an outlier of std "
        f"σ₂ = {bundle['sigma2']} rad (Laplacian, scale σ₂/√2, or uniform ±√3σ₂), else N(0, σ₁²) with "
        f"σ₁ = {bundle['sigma1']} rad. SNR = 10·log10(1/((1−p)σ₁² + pσ₂²)). p ∈ "
        f"{{{', '.join(str(p) for p in SWEEP_P)}}}.",
        "",
        "Methods (all at the last epoch, all 120 bearings):",
        "",
        "* `EKF` — EKFT on raw bearings (σ₁ assumed). It and the IMMs start from the robust initialiser "
        "(the scenario's `init = \"robust\"`: the best-supported bearing pair of the first 5 epochs), not the "
        "thesis's first pair, which holds an outlier in 1 − (1 − p)² of the runs.",
        f"* `LOO` — leave-one-out (document 003): batch Torrieri/Gauss–Newton fix on all bearings, dropping the "
        f"bearing with the largest studentised residual while it exceeds {bundle['gate']} σ (`TORRIERI` with "
        "`gate`, run as one epoch).",
        "* `ML` — the same batch fix without rejection (the Gaussian ML fix).",
        "* `IMM (symmetric)` / `IMM (iid)` — two EKFTs (σ₁, σ₂), p matched to the jammer's, transition "
        "[[1−p, p], [p, 1−p]] (the source documents') or rows [1−p, p] (i.i.d. contamination).",
        "* `CRB` — the static-emitter bound with each bearing's Fisher information taken from the actual "
        "mixture density (`fusion.crb3d.noise_fisher_information`). For uniform outliers the density jumps at "
        "±√3σ₂, the CRB's regularity conditions fail and the bound is indicative only.",
        "",
        "All points share the scenario's seed, and the emulators draw the same variates whatever the jamming "
        "does with them, so the clean Gaussian part of the noise is the same draw at every p: the points are "
        f"correlated, and a lucky or unlucky sample of {runs} runs shows at all of them alike (for instance "
        "batch fixes below the bound at every p).",
        "",
    ]
    for law in SWEEP_LAWS:
        if (law, "mse") not in tables:
            continue
        text += [f"## {law.capitalize()} outliers", "", "Final mean-square position error, m²:", "",
                 tables[(law, "mse")], "", "Textbook CEP50 (median miss of the final fixes), m:", "",
                 tables[(law, "cep")], ""]
    text += ["## Verdict", "", *_sweep_verdicts(bundle), "",
             "## Plot", "", f"![MS error and CEP50 against SNR](jammed-df-sweep/{png})", ""]
    return write_report(out_dir, "jammed-df-sweep", bundle, text)
