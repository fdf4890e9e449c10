"""The bootstrap benchmark's figures: what ``make bench`` writes for each body (issue 21)."""

from body_scheme_apps.bootstrap_bench import BODIES, bootstrap_body, table


def test_a_body_bootstraps_lazily_with_the_figures_the_benchmark_writes():
    lazy = bootstrap_body("paper6", eager=False)
    assert set(lazy) == {"updates_per_s", "max_update_ms", "peak_mb", "candidates_max", "raced", "steps", "finished",
                         "true_tree"}
    assert lazy["finished"] and lazy["true_tree"] and lazy["raced"] > 0
    assert lazy["candidates_max"] == 21 * (1 + 3 * 6)  # complexity <= 1 only: C(7, 2) pairs x (static + 3 x 6)
    assert lazy["updates_per_s"] > 0 and lazy["max_update_ms"] > 0 and lazy["peak_mb"] >= 0
    result = {f"bootstrap_paper6_{infix}{key}": value for infix in ("", "eager_") for key, value in lazy.items()}
    assert "paper6 updates_per_s" in table(result, ["paper6"]) and set(BODIES) == {"paper6", "arm7", "dualarm",
                                                                                    "upper18"}
