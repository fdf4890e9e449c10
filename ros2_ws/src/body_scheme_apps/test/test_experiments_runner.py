"""Tests of the experiments' runner, report and command line."""

import json
import math
import types

import pytest

from body_scheme_apps.experiments import runner
from body_scheme_apps.experiments.__main__ import main
from body_scheme_apps.experiments.report import met, write_results_md

pytestmark = pytest.mark.slow  # make test-fast leaves it out (docs/architecture.md, Tests)


def test_aggregate_gives_nan_aware_mean_and_std_twins_and_skips_curves():
    """Mean and std over runs per scalar key, NaN runs left out, curves and events not aggregated."""
    runs = [{"a": 1.0, "b": math.nan, "curves": {}}, {"a": 3.0, "b": 2.0, "curves": {}}]
    summary = runner.aggregate(runs)
    assert summary == {"a": 2.0, "a_std": 1.0, "b": 2.0, "b_std": 0.0}


def test_sanity_problems_flag_non_finite_and_out_of_bounds_figures():
    """NaN and out-of-bounds figures are reported; _std twins and unbounded keys are not checked against bounds."""
    problems = runner.sanity_problems({"a": math.nan, "b": 5.0, "b_std": math.nan, "c": 1e9},
                                      {"b": (0.0, 1.0)})
    assert problems == ["a is nan", "b = 5 outside the sanity bounds (0.0, 1.0)"]


def test_a_failing_run_is_reported_with_its_task_and_the_others_go_on():
    """An exception in one run becomes that outcome's error text; an unknown experiment is one such error."""
    outcomes = runner.run_tasks([runner.Task("nope", 0, "noise"), runner.Task("table1", 0, "bad-mode")], jobs=1,
                                progress=False)
    assert "unknown experiment 'nope'" in outcomes[0].error
    assert "perception must be" in outcomes[1].error and outcomes[1].result == {}


def test_report_marks_missed_targets_plainly(tmp_path):
    """RESULTS.md shows paper, target, ours and a bold 'no' for a missed target, listed again under 'Targets missed'."""
    module = types.ModuleType("fake", "A title\n\nThe protocol.")
    module.FIGURES = {"x_mm": "the x error", "y": "the y count"}
    module.PAPER, module.TARGETS = {"x_mm": 50.0}, {"x_mm": 30.0, "y": 2.0}
    noise = {"x_mm": 41.0, "x_mm_std": 3.0, "y": 1.0, "y_std": 0.0}
    meta = {"commit": "abc", "seed": 0, "runs": 2, "rendered_runs": 0, "jobs": 1, "seconds": 1.0}
    path = write_results_md(tmp_path / "R.md", {"fake": module}, noise, {}, {}, meta, "make experiments")
    text = path.read_text()
    assert "## A title" in text and "The protocol." in text
    assert "| `x_mm` | 50.0 | <= 30.0 | 41.0 ± 3.0 | n/a | **no** |" in text
    assert "| `y` | n/a | <= 2.00 | 1.00 ± 0.00 | n/a | yes |" in text
    assert "- `x_mm`: 41.0 against the target <= 30.0 (paper 50.0)" in text
    assert met("y", math.nan, module.TARGETS) is None


def test_a_figure_where_higher_is_better_has_a_minimum_target(tmp_path):
    """MIN_TARGETS are shown as '>=' and met when the value reaches them."""
    module = types.ModuleType("fake", "A title\n\nThe protocol.")
    module.FIGURES, module.PAPER, module.TARGETS = {"fraction": "the fraction"}, {}, {}
    module.MIN_TARGETS = {"fraction": 0.96}
    meta = {"commit": "abc", "seed": 0, "runs": 2, "rendered_runs": 0, "jobs": 1, "seconds": 1.0,
            "runs_per_experiment": {"fake": 30}}
    text = write_results_md(tmp_path / "R.md", {"fake": module}, {"fraction": 0.9, "fraction_std": 0.3}, {}, {},
                            meta, "make experiments").read_text()
    assert "| `fraction` | n/a | >= 0.96 | 0.90 ± 0.30 | n/a | **no** |" in text and "30 noise-model runs." in text
    # The run count is said before the table, not inside it (a line between header and rows breaks the table).
    assert text.index("30 noise-model runs.") < text.index("| figure | paper |")
    assert met("fraction", 0.97, {}, module.MIN_TARGETS) and not met("fraction", 0.5, {}, module.MIN_TARGETS)


def test_a_figure_in_both_target_tables_has_a_range(tmp_path):
    """A coverage must be high enough and not too high (a bound that is right, not only safe): both limits shown,
    met only between them."""
    module = types.ModuleType("fake", "A title\n\nThe protocol.")
    module.FIGURES, module.PAPER = {"coverage": "the coverage"}, {}
    module.TARGETS, module.MIN_TARGETS = {"coverage": 0.98}, {"coverage": 0.9}
    meta = {"commit": "abc", "seed": 0, "runs": 2, "rendered_runs": 0, "jobs": 1, "seconds": 1.0}
    text = write_results_md(tmp_path / "R.md", {"fake": module}, {"coverage": 0.999, "coverage_std": 0.0}, {}, {},
                            meta, "make experiments").read_text()
    assert "| `coverage` | n/a | >= 0.90 and <= 0.98 | 1.00 ± 0.00 | n/a | **no** |" in text
    assert [met("coverage", v, module.TARGETS, module.MIN_TARGETS) for v in (0.85, 0.95, 0.99)] == [False, True,
                                                                                                   False]


def test_command_writes_results_json_with_seed_commit_and_std_twins(tmp_path, capsys):
    """One quick run end to end (Fig. 7: one of the cheapest with a plot; each experiment's own run is tested in its
    test file): results.json has the figures, _std twins, seed, commit and runs; --check passes."""
    code = main(["--only", "fig7", "--runs", "1", "--rendered-runs", "0", "--quick", "--jobs", "1", "--quiet",
                 "--out", str(tmp_path), "--md", str(tmp_path / "RESULTS.md"), "--check"])
    assert code == 0
    results = json.loads((tmp_path / "results.json").read_text())
    assert results["seed"] == 0 and results["runs"] == 1 and results["commit"]
    assert math.isfinite(results["fig7_pred_err_mm_50"]) and "fig7_pred_err_mm_50_std" in results
    assert results["rendered"] == {}
    assert (tmp_path / "fig7.png").exists() and "fig7.png" in (tmp_path / "RESULTS.md").read_text()


def test_keep_reruns_one_experiment_and_keeps_the_others_figures(tmp_path):
    """--only transmission --keep over an earlier Fig. 7 run: results.json and RESULTS.md have both (and the
    Fig. 7 plot), the seconds add up."""
    common = ["--runs", "1", "--rendered-runs", "0", "--quick", "--jobs", "1", "--quiet", "--out", str(tmp_path),
              "--md", str(tmp_path / "RESULTS.md")]
    assert main(["--only", "fig7", *common]) == 0
    first = json.loads((tmp_path / "results.json").read_text())
    plots = sorted(p.name for p in tmp_path.glob("fig7*.png"))
    assert main(["--only", "transmission", "--keep", *common]) == 0
    results = json.loads((tmp_path / "results.json").read_text())
    assert results["fig7_pred_err_mm_50"] == first["fig7_pred_err_mm_50"] and plots
    assert math.isfinite(results["transmission_ee_err_mm"]) and results["seconds"] >= first["seconds"]
    assert set(results["runs_per_experiment"]) == {"fig7", "transmission"}
    text = (tmp_path / "RESULTS.md").read_text()
    assert all(name in text for name in plots) and "transmission" in text and "--keep" in text


def test_keep_needs_an_earlier_results_file(tmp_path):
    with pytest.raises(SystemExit, match="earlier"):
        main(["--only", "zoo", "--keep", "--quick", "--runs", "1", "--rendered-runs", "0", "--jobs", "1", "--quiet",
              "--out", str(tmp_path)])


def test_command_rejects_bad_run_counts():
    """--runs 0 is a usage error."""
    with pytest.raises(SystemExit):
        main(["--runs", "0"])


def test_a_run_into_another_directory_writes_its_report_there(tmp_path, monkeypatch):
    """Without --md, a run with --out elsewhere writes RESULTS.md beside its results.json, not docs/RESULTS.md."""
    monkeypatch.chdir(tmp_path)
    assert main(["--only", "transmission", "--runs", "1", "--rendered-runs", "0", "--quick", "--jobs", "1",
                 "--quiet", "--out", "elsewhere"]) == 0
    assert (tmp_path / "elsewhere" / "RESULTS.md").is_file() and not (tmp_path / "docs").exists()


def test_a_failing_plot_keeps_the_figures_and_fails_the_command(tmp_path, monkeypatch, capsys):
    """A plot that raises after a long run: results.json still has the experiment's figures, the error is printed
    and the command exits 1."""
    from body_scheme_apps.experiments import transmission

    def broken(runs, path_prefix):
        raise TypeError("Object of type int64 is not JSON serializable")

    monkeypatch.setattr(transmission, "plot", broken)
    assert main(["--only", "transmission", "--runs", "1", "--rendered-runs", "0", "--quick", "--jobs", "1",
                 "--quiet", "--out", str(tmp_path), "--md", str(tmp_path / "RESULTS.md")]) == 1
    assert math.isfinite(json.loads((tmp_path / "results.json").read_text())["transmission_ee_err_mm"])
    assert "transmission's plot: TypeError" in capsys.readouterr().err
