"""The psychometric fit, detection intervals, Pareto set and cheapest indistinguishable level (issue 38):
against psignifit 4 (its demo data and simulated exports) and planted observers."""

from __future__ import annotations

import hashlib
import json
import math
import os
import warnings
import xml.etree.ElementTree as ET
from importlib import metadata
from pathlib import Path

import numpy as np
import pytest

from server.analysis import psychometric as pm
from server.analysis.thresholds import PPS_LEVELS, Observer, constant_stimuli, run

# psignifit's demo_001 (2AFC, 90 trials per level): stimulus level, correct, trials
DEMO = np.array([[0.0010, 45, 90], [0.0015, 50, 90], [0.0020, 44, 90], [0.0025, 44, 90], [0.0030, 52, 90],
                 [0.0035, 53, 90], [0.0040, 62, 90], [0.0045, 64, 90], [0.0050, 76, 90], [0.0060, 79, 90],
                 [0.0070, 88, 90], [0.0080, 90, 90], [0.0100, 90, 90]])

# Agreement with psignifit 4.3 (MAP under its default priors, overdispersion eta fitted; ours: maximum likelihood
# with the lapse in [0, 0.1]), measured while building:
# - its demo_001 (13 levels x 90 trials, linear scale): threshold 0.0046478 vs 0.0046464 (0.03 %), width
#   0.0046591 vs 0.0046632 (0.09 %).  Tolerance 1 % and 3 %: an order of magnitude above what was measured, far
#   below the threshold's own 95 % interval (about +-6 %).
# - 20 simulated exports (7 pps levels x 20 trials, log10 scale, planted threshold 10 pps, width 0.6): median
#   |threshold difference| 0.0035 log10 units (max 0.076, on a seed whose width neither pins down), median width
#   ratio 0.98 (range 0.32 ... 1.07: with 20 trials a level, psignifit's width prior pulls an ill-determined width
#   up, maximum likelihood lets it go steep); psignifit's estimates inside our 95 % bootstrap intervals in 20 of
#   20.  Tolerances: median |difference| <= 0.01 log10 units (2.3 % of the level), every one <= 0.1, median width
#   ratio within 0.9 ... 1.1, psignifit's estimates inside our intervals in >= 19 of 20.
DEMO_THRESHOLD_RTOL = 0.01
DEMO_WIDTH_RTOL = 0.03


def _psignifit(data: np.ndarray) -> dict:
    ps = pytest.importorskip("psignifit")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = ps.psignifit(data, sigmoid="norm", experiment_type="2AFC", verbose=False)
    return {**r.parameter_estimate, "ci": r.confidence_intervals}


def test_demo_data_agrees_with_psignifit() -> None:
    ours = pm.fit(DEMO[:, 0], DEMO[:, 2], DEMO[:, 1], log_scale=False, bootstrap=300)
    ref = _psignifit(DEMO)
    assert ours.increasing
    assert ours.threshold.estimate == pytest.approx(ref["threshold"], rel=DEMO_THRESHOLD_RTOL)
    assert ours.width.estimate == pytest.approx(ref["width"], rel=DEMO_WIDTH_RTOL)
    # psignifit's 95 % credible interval of the threshold and our bootstrap one overlap
    lo, hi = ref["ci"]["threshold"]["0.95"]
    assert ours.threshold.low < hi and lo < ours.threshold.high
    # the profile-likelihood interval too: psignifit's 95 % interval 0.004251 … 0.004932, ours 0.004319 …
    # 0.004994 (measured: within 2 %); tolerance 5 %

    assert ours.threshold_profile is not None
    assert ours.threshold_profile.low == pytest.approx(lo, rel=0.05)
    assert ours.threshold_profile.high == pytest.approx(hi, rel=0.05)


# psignifit's estimates for the simulated exports below, recorded (psignifit takes about 0.8 s a fit, 16 s for the
# 20): each entry is used only for the very data it was computed from (a SHA-256 of the array) and this psignifit
# version, any other export is fitted there and then; the first export is always fitted again and must give its
# recorded numbers.  `ANIMSTUDY_RECORD_PSIGNIFIT=1 pytest -k agree_with_psignifit` writes the file anew.
PSIGNIFIT_RECORDED = Path(__file__).parent / "reference" / "psignifit_simulated_exports.json"


def _psignifit_recorded(datasets: list[np.ndarray]) -> list[dict]:
    version = metadata.version("psignifit")
    record = bool(os.environ.get("ANIMSTUDY_RECORD_PSIGNIFIT"))
    recorded = json.loads(PSIGNIFIT_RECORDED.read_text()) if PSIGNIFIT_RECORDED.exists() else {}
    known = recorded.get("fits", {}) if recorded.get("psignifit") == version and not record else {}
    refs = []
    for k, data in enumerate(datasets):
        key = hashlib.sha256(np.ascontiguousarray(data, np.float64).tobytes()).hexdigest()
        if k == 0 or key not in known:
            fitted = _psignifit(data)
            fitted = {"threshold": float(fitted["threshold"]), "width": float(fitted["width"])}
            if key in known:
                assert fitted == pytest.approx(known[key], rel=1e-9), "the recorded psignifit fits are not its own"
            known[key] = fitted
        refs.append(known[key])
    if record:
        PSIGNIFIT_RECORDED.write_text(json.dumps({"psignifit": version, "fits": known}, indent=1) + "\n")
    return refs


def test_simulated_exports_agree_with_psignifit() -> None:
    obs = Observer(threshold=10.0, width=0.6, lapse=0.02)
    diffs, ratios, inside = [], [], 0
    exports = [constant_stimuli(obs, PPS_LEVELS, 20, np.random.default_rng(seed)) for seed in range(20)]
    # psignifit fits rising sigmoids in the space it is given: -log10(level)
    refs = _psignifit_recorded([np.column_stack([-np.log10(c.levels), c.correct, c.trials]) for c in exports])
    for seed, (c, ref) in enumerate(zip(exports, refs, strict=True)):
        ours = pm.fit(c.levels, c.trials, c.correct, increasing=False, bootstrap=200, seed=seed)
        diffs.append(abs(-ours.log_threshold.estimate - ref["threshold"]))
        ratios.append(ours.width.estimate / ref["width"])
        inside += ours.log_threshold.contains(-ref["threshold"]) and ours.width.contains(ref["width"])
    assert np.median(diffs) <= 0.01
    assert max(diffs) <= 0.1
    assert 0.9 <= np.median(ratios) <= 1.1
    assert inside >= 19


def test_fit_recovers_an_exact_function() -> None:
    """Expected counts of a known function (no noise, many trials): its parameters come back."""
    obs = Observer(threshold=12.0, width=0.4, lapse=0.03)
    lv = np.array(PPS_LEVELS, dtype=float)
    n = np.full(len(lv), 100_000)
    f = pm.fit(lv, n, np.round(n * obs.p(lv)).astype(int), bootstrap=20, steps=(241, 81, 11))
    assert not f.increasing
    assert f.threshold.estimate == pytest.approx(12.0, rel=0.005)
    assert f.width.estimate == pytest.approx(0.4, rel=0.01)
    assert f.lapse.estimate == pytest.approx(0.03, abs=0.003)
    # slope at threshold per log10 unit: (1 - 0.5 - 0.03) * phi(0) / s, s = 0.4 / (2 * 1.6449)
    assert f.slope.estimate == pytest.approx(0.47 * 0.398942 / (0.4 / 3.289707), rel=0.01)


def test_fit_rejects_too_few_levels_and_bad_counts() -> None:
    with pytest.raises(ValueError, match="3 levels"):
        pm.fit([4, 8, 8], [10, 10, 10], [5, 6, 7])
    with pytest.raises(ValueError, match="outside"):
        pm.fit([4, 8, 16], [10, 10, 10], [5, 6, 11])


def test_detection_intervals_are_clopper_pearson() -> None:
    (d,) = pm.detection([8], [20], [15])
    assert d.p == 0.75
    # Clopper-Pearson 95 % for 15/20 (beta quantiles, tabulated): 0.5090 … 0.9134
    assert d.low == pytest.approx(0.5090, abs=5e-4)
    assert d.high == pytest.approx(0.9134, abs=5e-4)
    (w,) = pm.detection([8], [20], [15], method="wilson")
    assert w.low == pytest.approx(0.5313, abs=5e-4) and w.high == pytest.approx(0.8881, abs=5e-4)


def test_pareto_and_cheapest_indistinguishable() -> None:
    assert pm.pareto([1, 2, 3, 2], [0.9, 0.7, 0.6, 0.8]) == [True, True, True, False]
    rows = [("pps4", 4, 40, 38), ("pps8", 8, 40, 30), ("pps12", 12, 40, 22), ("pps24", 24, 40, 20),
            ("pps30", 30, 40, 21)]
    costs = {"pps4": 1.0, "pps8": 1.5, "pps12": 2.0, "pps24": 3.5, "pps30": 4.0}
    f = pm.frontier("walk", rows, costs, bootstrap=50)
    by = {p.condition: p for p in f.points}
    # 22/40: Clopper-Pearson upper bound 0.7 < 0.75; 30/40: upper bound 0.87
    assert by["pps12"].indistinguishable and not by["pps8"].indistinguishable
    assert f.cheapest_indistinguishable is not None and f.cheapest_indistinguishable.condition == "pps12"
    assert [p.condition for p in f.points if p.pareto] == ["pps4", "pps8", "pps12", "pps24"]
    assert f.fit is not None and 8 < f.fit.threshold.estimate < 12


def test_frontier_names_conditions_without_cost() -> None:
    with pytest.raises(ValueError, match="pps4"):
        pm.frontier("walk", [("pps4", 4, 10, 9)], {}, fit_function=False)


def test_svg_parses_and_marks_the_cheapest() -> None:
    from server.analysis.frontier_plot import svg

    rows = [("pps4", 4, 40, 38), ("pps8", 8, 40, 30), ("pps12", 12, 40, 22), ("pps24", 24, 40, 20)]
    f = pm.frontier("walk", rows, {"pps4": 1.0, "pps8": 1.5, "pps12": 2.0, "pps24": 3.5}, bootstrap=50)
    root = ET.fromstring(svg([f]))
    ns = "{http://www.w3.org/2000/svg}"
    assert root.tag == f"{ns}svg"
    circles = root.findall(f".//{ns}circle")
    points = [c for c in circles if c.get("data-condition")]
    assert len(points) == 4
    assert len([c for c in circles if c.get("class") == "cheapest"]) == 1
    assert [c.get("data-condition") for c in points if c.get("data-cheapest") == "true"] == ["pps12"]
    assert {c.get("data-condition") for c in points if c.get("data-pareto") == "true"} == {
        "pps4", "pps8", "pps12", "pps24"}
    assert any("walk" in (t.text or "") for t in root.iter(f"{ns}text"))


def _coverage(design: str, trials: int, seeds: int, profile: bool = False) -> float:
    obs = Observer(threshold=10.0, width=0.5, lapse=0.02)
    runs = [run(design, obs, PPS_LEVELS, trials, s, bootstrap=200) for s in range(seeds)]
    return float(np.mean([r.covered_profile if profile else r.covered for r in runs]))


@pytest.mark.slow
def test_constant_stimuli_recovers_planted_threshold_in_90_percent() -> None:
    """100 seeds, 7 levels x 20 trials: the threshold's 95 % bootstrap interval holds the planted one in >= 90 %
    (measured: 0.95 on 20 seeds while building; ~40 s)."""
    assert _coverage("constant-stimuli", 140, 100) >= 0.9


@pytest.mark.slow
def test_quest_plus_recovers_planted_threshold_in_90_percent() -> None:
    """100 seeds, 60 QUEST+ trials each (server.analysis.quest, 4 ms a staircase; it was 1-5 s through questplus).  The
    profile-likelihood interval: the parametric bootstrap at the observed counts per level ignores that QUEST+
    chose the levels from the answers, and covered 86 % of 100 seeds (measured), below the 90 % asked."""
    assert _coverage("staircase", 60, 100, profile=True) >= 0.9


def test_constant_stimuli_coverage_quick() -> None:
    """The fast guard of the slow test: 20 seeds, >= 80 % (at a true 95 % the chance of < 80 % is ~1.6 %, and
    the seeds are fixed)."""
    assert _coverage("constant-stimuli", 140, 20) >= 0.8


def test_observer_probability_at_threshold() -> None:
    o = Observer(threshold=10.0, width=0.5, lapse=0.02)
    assert o.p(np.array([10.0]))[0] == pytest.approx(0.5 + 0.48 / 2)
    assert math.isclose(o.p(np.array([1000.0]))[0], 0.5, abs_tol=1e-6)


def _manifest(tmp_path, costs: dict[str, float]):
    from server.clipset.manifest import MANIFEST, ClipEntry, ClipManifest, write_json

    clips = [ClipEntry(id=f"walk-{c}", animation="walk", kind="gait", condition=c, method="update_rate",
                       params={"rate": int(c[3:])}, key_count=10, duration_s=1.0, fps=30, frames=30,
                       playback="loop", in_place=True, root_speed_mps=0.0,
                       metrics={"cost_ms_per_1000": v, "bytes": 1000 * v}, source={}, file=f"walk-{c}.npz",
                       ladder="pps", level=int(c[3:])) for c, v in costs.items()]
    write_json(tmp_path / MANIFEST, ClipManifest(clips=clips))
    return tmp_path


def test_study_frontier_command_over_an_export(tmp_path, capsys) -> None:
    import csv
    import json

    from server import cli

    answers = {"pps4": (40, 38), "pps8": (40, 30), "pps12": (40, 22), "pps24": (40, 20)}
    rows = []
    for c, (n, k) in answers.items():
        rows += [{"animation": "walk", "test_condition": c, "level": c[3:], "correct": str(i < k).lower(),
                  "catch": "false", "practice": "false", "session_id": f"s{i % 2}"} for i in range(n)]
    rows.append({"animation": "walk", "test_condition": "pps4", "level": "4", "correct": "false", "catch": "true",
                 "practice": "false", "session_id": "s0"})  # a catch trial: not counted
    export = tmp_path / "votes.csv"
    with export.open("w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    (tmp_path / "clips").mkdir()
    clips = _manifest(tmp_path / "clips", {"pps4": 1.0, "pps8": 1.5, "pps12": 2.0, "pps24": 3.5})
    out_svg = tmp_path / "f.svg"
    assert cli.main(["study", "frontier", str(export), "--manifest", str(clips), "--svg", str(out_svg)]) == 0
    (walk,) = json.loads(capsys.readouterr().out)
    assert walk["cheapest_indistinguishable"]["condition"] == "pps12"
    assert [p["detection"]["trials"] for p in walk["points"]] == [40, 40, 40, 40]
    assert walk["fit"]["threshold"]["low"] <= walk["fit"]["threshold"]["estimate"] <= walk["fit"]["threshold"]["high"]
    assert sorted(walk["participants"]) == ["s0", "s1"]  # each participant's own fit
    assert all(p["trials"] == 80 for p in walk["participants"].values())
    ET.fromstring(out_svg.read_text())
    # bytes as the cost
    assert cli.main(["study", "frontier", str(export), "--manifest", str(clips), "--metric", "bytes"]) == 0
    assert json.loads(capsys.readouterr().out)[0]["points"][0]["cost"] == 1000.0


def test_study_frontier_command_without_threshold_rows(tmp_path, capsys) -> None:
    from server import cli

    export = tmp_path / "votes.json"
    export.write_text('[{"animation": "walk", "test_condition": "hybrid1", "level": "", "correct": ""}]')
    (tmp_path / "clips").mkdir()
    clips = _manifest(tmp_path / "clips", {"pps4": 1.0})
    assert cli.main(["study", "frontier", str(export), "--manifest", str(clips)]) == 1
    assert "no answered threshold trials" in capsys.readouterr().err


def test_threshold_plan_command(capsys) -> None:
    from server import cli

    # a generous target (0.8 log10 units) is met at the first trial count of each design: 20 trials, rounded
    # down to whole repeats of the 7 levels for constant stimuli (14)
    assert cli.main(["study", "threshold-plan", "--levels", "4,6,8,12,16,24,30", "--width", "0.8",
                     "--seeds", "2"]) == 0
    out = capsys.readouterr().out
    assert "constant-stimuli: 14 trials" in out and "staircase: 20 trials" in out and "QUEST+ / constant" in out
    assert cli.main(["study", "threshold-plan", "--levels", "4,4,8"]) == 2


def test_simulate_and_plan_of_a_threshold_design(capsys) -> None:
    """The hook `study simulate`/`plan` take for a design whose mode is a threshold mode (the design as the
    study-file parser makes it, settled against its clip set: level_order(), detectable_at, trials, repeats)."""
    import argparse
    from types import SimpleNamespace

    from server.cli import thresholds as tc

    design = SimpleNamespace(mode="constant-stimuli", repeats=2, trials=None, detectable_at="low",
                             level_order=lambda: {f"pps{v}": v for v in PPS_LEVELS})
    args = argparse.Namespace(study_command="simulate", seeds=3, threshold=None, slope_width=0.5, width=0.8)
    assert tc.simulate_or_plan(args, design) == 0
    out = capsys.readouterr().out
    assert "constant-stimuli 28 trials" in out and "observer threshold 10.95" in out
    args.study_command = "plan"
    assert tc.simulate_or_plan(args, design) == 0
    assert "14 trials per participant and animation" in capsys.readouterr().out


def test_simulate_the_update_rate_study(capsys, tmp_path, monkeypatch) -> None:
    """`study simulate` of the issue's study file (2AFC staircase over pps) goes through the threshold hook, with
    the levels of its clip set: named by [clips] set (read, not built), or the server's built clip set; with
    neither it says where the levels come from."""
    from pathlib import Path

    from server import cli

    repo = Path(__file__).resolve().parent.parent
    monkeypatch.setenv("ANIMSTUDY_VAR_DIR", str(tmp_path / "var"))  # no clip set built there
    study = repo / "studies" / "update-rate.toml"
    assert cli.main(["study", "simulate", str(study), "--participants", "1", "--seeds", "2"]) == 2
    assert "the levels of ladder 'pps' come from the clip set's manifest" in capsys.readouterr().err
    named = tmp_path / "update-rate.toml"
    named.write_text(study.read_text(encoding="utf-8") + f'\n[clips]\nset = "{repo}/server/clipset/update-rate.toml"\n',
                     encoding="utf-8")
    assert cli.main(["study", "simulate", str(named), "--participants", "1", "--seeds", "2"]) == 0
    out = capsys.readouterr().out
    assert "staircase design over 6 levels" in out and "threshold interval median" in out
