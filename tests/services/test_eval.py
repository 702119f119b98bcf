"""The Monte Carlo evaluation: common random numbers, parallel = serial, the ``zfusion
eval`` command (table, JSON, report, progress), and the reproduction reports — every
number in their Markdown tables is the number in the JSON beside them."""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest
from scipy.stats import chi2

from sensors_sim import load_scenario
from services.cli import main
from services.evaluation import Variant, default_methods, evaluate, merged_measurements, run_method, variants_for
from services.scoring import truth_function
from services.summary import method_summary
from conftest import ROOT

ROOT = ROOT
RESULTS = ROOT / "docs" / "results"
DESIGN_KEYS = {"rmse_pos", "rmse_vel", "rmse_acc", "cep50", "anees", "n_updates", "series"}


# Markdown tables ----------------------------------------------------------------------
def md_tables(text: str) -> list[list[dict[str, str]]]:
    """Every pipe table of a Markdown text, as lists of {header: cell}."""
    tables, lines = [], text.splitlines()
    i = 0
    while i < len(lines):
        if lines[i].startswith("|") and i + 1 < len(lines) and re.match(r"^\|(-+\|)+$", lines[i + 1]):
            head = [c.strip() for c in lines[i].strip("|").split("|")]
            rows, i = [], i + 2
            while i < len(lines) and lines[i].startswith("|"):
                rows.append(dict(zip(head, (c.strip() for c in lines[i].strip("|").split("|")))))
                i += 1
            tables.append(rows)
        else:
            i += 1
    return tables


def same(cell: str, value) -> bool:
    """A table cell shows ``value`` (to the precision it is printed with)."""
    cell = cell.strip().strip("*")
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return cell == "—"
    if cell == "—":
        return False
    x = float(cell)
    if "e" in cell:
        return math.isclose(x, value, rel_tol=6e-4)
    decimals = len(cell.split(".")[1]) if "." in cell else 0
    return abs(x - value) <= 0.5 * 10.0**-decimals + 1e-9 * abs(value)


def steps_inside(series, dof, runs):
    lo, hi = chi2.ppf(0.025, dof * runs) / runs, chi2.ppf(0.975, dof * runs) / runs
    vals = [v for v in series if v is not None]
    return float(np.mean([(lo <= v <= hi) for v in vals]))


# Checks of a report against its JSON --------------------------------------------------------
def check_patent(md: str, bundle: dict) -> int:
    ev = bundle["evaluations"]
    runs = bundle["runs"]
    t_all, t_half = md_tables(md)[:2]
    crb = ev["naive"]["crb"]
    n = 0
    for row, half in zip(t_all, t_half):
        method, rule = row["method"], row["fusion rule"]
        if method == "**CRB**":
            assert same(row["pos (m)"], crb["overall"]["rmse_pos"]) and same(row["vel (m/s)"], crb["overall"]["rmse_vel"])
            assert same(half["pos (m)"], crb["second_half"]["rmse_pos"])
            continue
        doc = ev["radar3d"] if method == "RADAR3D" else ev["naive" if rule == "—" else rule]
        m = doc["methods"][method]
        assert (half["method"], half["fusion rule"]) == (method, rule)
        assert same(row["pos (m)"], m["rmse_pos"]), (method, rule)
        assert same(row["vel (m/s)"], m["rmse_vel"]) and same(row["acc (m/s²)"], m["rmse_acc"])
        assert same(row["ANEES"], m["anees"])
        assert same(row["pos / CRB"], m["rmse_pos"] / crb["overall"]["rmse_pos"])
        assert same(row["steps in χ²"], steps_inside(m["series"]["anees"], 9, runs))
        assert same(half["pos (m)"], m["second_half"]["rmse_pos"]) and same(half["vel (m/s)"], m["second_half"]["rmse_vel"])
        assert same(half["vel / CRB"], m["second_half"]["rmse_vel"] / crb["second_half"]["rmse_vel"])
        assert same(half["ANEES"], m["second_half"]["anees"])
        n += 1
    return n


def check_thesis(md: str, bundle: dict) -> int:
    mp, cep, rmse, nees = md_tables(md)[:4]
    n = 0
    for a, b, c, d in zip(mp, cep, rmse, nees):
        doc = bundle["evaluations"][a["scenario"]]
        ms = doc["methods"]
        for m in ("EKF", "MEKF1", "MEKF2", "MEKF3", "MEKF4", "MEKF5"):
            assert same(a[f"{m} (thesis)"].split(" (")[0], ms[m]["median_point_distance"])
        for m in ("EKF", "MEKF1", "MEKF2", "MEKF3", "MEKF4", "MEKF5", "TORRIERI", "KF+TR", "MKF+TR"):
            if m not in ms:
                assert b[m] == c[m] == d[m] == "—"
                continue
            assert same(b[m], ms[m]["cep50"]) and same(c[m], ms[m]["final"]["rmse_pos"])
            assert same(d[m], ms[m]["series"]["anees"][-1])
            n += 1
        assert same(b["CRB"], doc["crb"]["cep50"]) and same(c["CRB"], doc["crb"]["rmse_pos_final"])
    return n


def check_sweep(md: str, bundle: dict) -> int:
    tables = md_tables(md)
    laws = [law for law in ("laplacian", "uniform") if any(p["law"] == law for p in bundle["points"])]
    assert len(tables) == 2 * len(laws)
    n = 0
    for i, law in enumerate(laws):
        mse, cep = tables[2 * i], tables[2 * i + 1]
        pts = [p for p in bundle["points"] if p["law"] == law]
        assert len(pts) == len(mse) == len(cep)
        for pt, row, crow in zip(pts, mse, cep):
            snr = 10 * math.log10(1 / ((1 - pt["p"]) * bundle["sigma1"] ** 2 + pt["p"] * bundle["sigma2"] ** 2))
            for r in (row, crow):
                assert same(r["p"], pt["p"]) and same(r["SNR (dB)"], snr)
            for label, m in pt["doc"]["methods"].items():
                assert same(row[label], m["final"]["mse_pos"]) and same(crow[label], m["cep50"])
                n += 1
            assert same(row["CRB"], pt["doc"]["crb"]["rmse_pos_final"] ** 2)
            assert same(crow["CRB"], pt["doc"]["crb"]["cep50"])
    return n


def check_many(md: str, bundle: dict) -> int:
    (table,) = md_tables(md)[:1]
    methods = bundle["evaluation"]["methods"]
    runs = bundle["runs"]
    ref = methods.get(bundle["criteria"]["reference"] or "")
    assert [r["method"].strip("`") for r in table] == list(methods)
    n = 0
    for row in table:
        m = methods[row["method"].strip("`")]
        assert same(row["GOSPA (m)"], m["gospa"]) and same(row["held"], m["held"])
        assert same(row["min hold"], m["worst_hold"]) and same(row["purity"], m["purity"])
        assert same(row["break %"], 100 * m["break_rate"])
        assert (int(row["breaks"]), int(row["tracks"]), int(row["false"]), int(row["ghost"])) == \
            (m["breaks"], m["tracks"], m["false_tracks"], m["longest_ghost"])
        assert row["all found"] == f"{m['all_found_runs']}/{runs}"
        if ref is not None:
            assert same(row[f"/ {bundle['criteria']['reference']}"], m["gospa"] / ref["gospa"])
        n += 1
    # one verdict line per method, saying meets exactly when every criterion holds
    for name in methods:
        line = next(x for x in md.splitlines() if x.startswith(f"* **{name}: "))
        assert ("meets" in line) == ("✗" not in line)
    return n


# The harness ------------------------------------------------------------------------------
def test_common_random_numbers_and_parallel_equals_serial():
    sc = load_scenario("patent-3d")
    variants = variants_for(["SS", "HNDD", "PHHNV"]) + [Variant("PHHNV/naive", "PHHNV", {"fusion_rule": "naive"})]
    serial = evaluate(sc, variants, 3)
    # SS and HNDD are the same update: identical only if fed identical measurements
    for k in ("rmse_pos", "rmse_vel", "anees"):
        assert serial["methods"]["SS"][k] == pytest.approx(serial["methods"]["HNDD"][k], rel=1e-9)
    assert serial["methods"]["PHHNV"]["rmse_pos"] == pytest.approx(serial["methods"]["SS"]["rmse_pos"], rel=1e-6)
    assert serial["methods"]["PHHNV/naive"]["variant"] == {"method": "PHHNV", "overrides": {"fusion_rule": "naive"},
                                                           "sensors": None}
    parallel = evaluate(sc, variants, 3, jobs=2)
    assert json.dumps(parallel, sort_keys=True) == json.dumps(serial, sort_keys=True)


def test_a_sensor_subset_sees_the_same_measurements():
    sc = load_scenario("patent-3d")
    full = merged_measurements(sc, 1)
    only = merged_measurements(sc, 1, ["angle"])
    assert only == [m for m in full if m.sensor == "angle"]
    # SS fuses both sensors: restricted to the angle sensor it is SS run on the angle
    # sensor's measurements of the same runs (no range: kilometres off), not SS
    a = evaluate(sc, [Variant("SS", "SS"), Variant("SS/angle", "SS", sensors=("angle",))], 2, crb=False)
    ref = method_summary([run_method(sc, "SS", run=r, measurements=merged_measurements(sc, r, ["angle"]))
                          for r in range(2)], truth_function(sc))
    got = a["methods"]["SS/angle"]
    assert got["series"]["rmse_pos"] == ref["series"]["rmse_pos"] and got["anees"] == ref["anees"]
    assert got["rmse_pos"] > 100 * a["methods"]["SS"]["rmse_pos"]


def test_default_methods_by_sensor_kinds():
    assert default_methods(load_scenario("patent-3d")) == ["RADAR2D", "ANGLE", "LCDD", "HNDD", "SS", "HNV", "PHHNV", "DDHNV"]
    assert "LCDD" not in default_methods(load_scenario("patent-3d-radar3d"))
    assert "HNDD" not in default_methods(load_scenario("patent-3d-separated"))
    fixed = default_methods(load_scenario("thesis-fixed-c1"))
    assert {"EKF", "MEKF3", "IMM", "KF+TR", "MKF+TR", "TORRIERI"} <= set(fixed)
    assert "KF+TR" not in default_methods(load_scenario("thesis-moving-9"))  # moving observer


def test_cli_eval_json_report_and_progress(tmp_path, capsys):
    out = tmp_path / "s.json"
    rep = tmp_path / "rep"
    assert main(["eval", "--scenario", "patent-3d", "--runs", "2", "--json", str(out), "--report", str(rep),
                 "--progress"]) == 0
    captured = capsys.readouterr()
    assert "run 2/2" in captured.err
    doc = json.loads(out.read_text())
    assert set(doc["methods"]) == {"RADAR2D", "ANGLE", "LCDD", "HNDD", "SS", "HNV", "PHHNV", "DDHNV"}
    assert {"scenario", "topology", "fusion_rule", "seed", "runs", "methods", "crb", "sources"} <= set(doc)
    for m in doc["methods"].values():
        assert DESIGN_KEYS <= set(m) and {"t", "rmse_pos", "anees"} <= set(m["series"])
        assert m["cep50"] is None and m["n_updates"] == 2 * 31
    assert doc["crb"]["t"] == doc["methods"]["SS"]["series"]["t"] and len(doc["crb"]["rmse_pos"]) == 31
    # the printed table carries the JSON's numbers and the bound
    ss_line = next(line for line in captured.out.splitlines() if line.startswith("SS "))
    assert float(ss_line.split()[1]) == pytest.approx(doc["methods"]["SS"]["rmse_pos"], abs=1e-4)
    assert any(line.startswith("CRB") for line in captured.out.splitlines())
    assert (rep / "report.md").is_file() and json.loads((rep / "summary.json").read_text()) == doc
    for png in ("rmse_pos.png", "rmse_vel.png", "nees.png", "nis.png"):
        assert (rep / png).read_bytes()[:4] == b"\x89PNG"


def test_cli_eval_emitter_fixes(tmp_path, capsys):
    out = tmp_path / "s.json"
    assert main(["eval", "--scenario", "thesis-fixed-c1", "--runs", "3", "--methods", "EKF", "MEKF3",
                 "--json", str(out), "--report", str(tmp_path / "r")]) == 0
    doc = json.loads(out.read_text())
    ekf = doc["methods"]["EKF"]
    assert ekf["rmse_vel"] is None and ekf["rmse_acc"] is None and ekf["cep50"] > 0
    assert ekf["median_point_distance"] is not None and len(ekf["final"]["err"]) == 3
    assert doc["crb"]["cep50"] > 0
    assert (tmp_path / "r" / "fixes.png").is_file()
    assert "median_pt" in capsys.readouterr().out


def test_cli_eval_rejects_bad_input(capsys):
    assert main(["eval", "--scenario", "patent-3d", "--runs", "0"]) == 2
    assert main(["eval", "--scenario", "patent-3d", "--runs", "1", "--methods", "NOPE"]) == 2
    assert "unknown method 'NOPE'" in capsys.readouterr().err


def check_moving(md: str, bundle: dict) -> int:
    runs, k0 = bundle["runs"], bundle["from_epoch"] - 1
    tables = md_tables(md)
    assert len(tables) == len(bundle["evaluations"])
    n = 0
    for table, (name, doc) in zip(tables, bundle["evaluations"].items()):
        crb = doc["crb"]
        bound = math.sqrt(np.mean(np.square(crb["rmse_pos"][k0:])))
        for row in table:
            if row["method"] == "**PCRB**":
                assert same(row["pos (m)"], crb["overall"]["rmse_pos"]) and same(row["pos from epoch 10 (m)"], bound)
                continue
            m = doc["methods"][row["method"].strip("`")]
            late = math.sqrt(np.mean(np.square(m["series"]["rmse_pos"][k0:])))
            assert same(row["pos (m)"], m["rmse_pos"]) and same(row["pos from epoch 10 (m)"], late), name
            assert same(row["/ PCRB"], late / bound) and same(row["vel (m/s)"], m["rmse_vel"])
            assert same(row["ANEES"], m["anees"]) and same(row["epochs in χ²"], steps_inside(m["series"]["anees"], 4, runs))
            n += 1
    return n


# The reproduction reports -------------------------------------------------------------------
def test_tiny_patent_report_tables_equal_their_json(tmp_path):
    from services import report

    b = report.build_patent("patent-3d", runs=2)
    md = report.write_patent_report(b, tmp_path).read_text()
    assert check_patent(md, json.loads((tmp_path / "patent-3d.json").read_text())) == 18
    assert (tmp_path / "patent-3d" / "rmse_pos.png").is_file()


def test_tiny_thesis_report_tables_equal_their_json(tmp_path):
    from services import report

    b = report.build_thesis(runs=2, scenarios=("thesis-moving-2", "thesis-fixed-c1"))
    md = report.write_thesis_report(b, tmp_path).read_text()
    assert check_thesis(md, json.loads((tmp_path / "thesis-cep.json").read_text())) == 7 + 9


def test_tiny_sweep_report_tables_equal_their_json(tmp_path):
    from services import report

    b = report.build_sweep(runs=2, ps=(0.3,))
    md = report.write_sweep_report(b, tmp_path).read_text()
    assert check_sweep(md, json.loads((tmp_path / "jammed-df-sweep.json").read_text())) == 2 * 5


def test_tiny_many_target_report_tables_equal_their_json(tmp_path, monkeypatch):
    import dataclasses

    import sensors_sim
    from services import report
    from services.report import many

    # the report's form, not its numbers: 15 of df-multi's 50 epochs (10 methods x 50 epochs were 15 CPU s)
    full = sensors_sim.load_scenario
    monkeypatch.setattr(many, "load_scenario", lambda ref: dataclasses.replace(full(ref), duration=15.0))
    b = report.build_many("df-multi", runs=1)
    assert b["evaluation"]["methods"] and all(m["steps"] == 15 for m in b["evaluation"]["methods"].values())
    md = report.write_many_report(b, tmp_path).read_text()
    assert check_many(md, json.loads((tmp_path / "df-multi.json").read_text())) == 10
    assert (tmp_path / "df-multi" / "gospa.png").is_file()


def test_tiny_moving_report_tables_equal_their_json(tmp_path):
    from services import report

    b = report.build_moving(runs=2, scenarios=("df-moving",))
    md = report.write_moving_report(b, tmp_path).read_text()
    assert check_moving(md, json.loads((tmp_path / "df-moving.json").read_text())) == 2
    assert (tmp_path / "df-moving" / "df-moving-rmse_pos.png").is_file()


@pytest.mark.parametrize("name,check", [("patent-3d", check_patent), ("patent-3d-60", check_patent),
                                        ("thesis-cep", check_thesis), ("jammed-df-sweep", check_sweep),
                                        ("air-picture", check_many), ("df-multi", check_many),
                                        ("df-moving", check_moving)])
def test_committed_reports_match_their_json(name, check):
    md, js = RESULTS / f"{name}.md", RESULTS / f"{name}.json"
    assert md.is_file() and js.is_file(), f"regenerate with: python -m services.report {name}"
    bundle = json.loads(js.read_text())
    assert check(md.read_text(), bundle) > 0
    assert f"python -m services.report {name}" in (RESULTS / "README.md").read_text()
    assert bundle["command"] in md.read_text()
