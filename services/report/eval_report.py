"""The report of one evaluation (``zfusion eval ... --report DIR``): its table, RMSE against
time per method with the Cramér–Rao bound, NEES and NIS against their χ² bounds, and for
emitter fixes a scatter of the final fixes with their error ellipses.
"""

from __future__ import annotations

from pathlib import Path

from ..summary import format_table
from .figures import (
    dofs_of,
    has_series,
    nees_band,
    nis_bands,
    nis_normalised,
    plot_fixes,
    plot_series,
    series_of,
)
from .tables import dumps


def write_eval_report(doc: dict, out_dir: Path, command: str = "") -> Path:
    """``report.md`` + ``summary.json`` + PNGs in ``out_dir`` for one evaluation."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "summary.json").write_text(dumps(doc) + "\n")
    crb = doc.get("crb") or {}
    bound = (crb.get("t", []), crb.get("rmse_pos", [])) if crb.get("t") else None
    figs = []
    if has_series(doc, "rmse_pos"):  # a many-target evaluation has GOSPA instead
        figs.append(("RMS position error", plot_series(series_of(doc, "rmse_pos"), out_dir / "rmse_pos.png",
                                                       "RMS position error (m)", f"{doc['scenario']}: position",
                                                       bound)))
    if has_series(doc, "rmse_vel"):
        vb = (crb["t"], crb["rmse_vel"]) if crb.get("rmse_vel") else None
        figs.append(("RMS velocity error", plot_series(series_of(doc, "rmse_vel"), out_dir / "rmse_vel.png",
                                                       "RMS velocity error (m/s)", f"{doc['scenario']}: velocity", vb)))
    if has_series(doc, "gospa"):
        figs.append(("Mean GOSPA", plot_series(series_of(doc, "gospa"), out_dir / "gospa.png", "mean GOSPA (m)",
                                               f"{doc['scenario']}: GOSPA ({doc['runs']} runs)")))
    if has_series(doc, "anees"):
        figs.append(("ANEES against its χ² interval", plot_series(
            series_of(doc, "anees"), out_dir / "nees.png", "average NEES",
            f"{doc['scenario']}: NEES ({doc['runs']} runs)", band=nees_band(doc))))
    nis = nis_normalised(doc)
    if any(any(v is not None for v in y) for _, y in nis.values()):
        dofs = [d for m in doc["methods"].values() for d in dofs_of(m["series"])]
        figs.append(("ANIS per degree of freedom against its χ² interval", plot_series(
            nis, out_dir / "nis.png", "average NIS / dof", f"{doc['scenario']}: NIS per dof (1 if consistent)",
            bands=nis_bands(dofs, doc["runs"]))))
    fixes = [n for n, m in doc["methods"].items() if (m.get("final") or {}).get("err")]
    if fixes:
        figs.append(("Final fixes, CEP and error ellipses",
                     plot_fixes(doc, fixes, out_dir / "fixes.png", f"{doc['scenario']}: final fixes")))
    text = [f"# Evaluation: {doc['scenario']}", ""]
    if command:
        text += [f"Command: `{command}`", ""]
    text += ["```", format_table(doc), "```", ""]
    for title, png in figs:
        text += [f"## {title}", "", f"![{title}]({png})", ""]
    path = out_dir / "report.md"
    path.write_text("\n".join(text))
    return path
