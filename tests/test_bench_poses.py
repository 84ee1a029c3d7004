"""``bench.poses --repeat``: the run reported among several."""

from bench.poses import _median_run


def test_the_median_run_is_reported_with_every_runs_error():
    runs = [{"ate_pct": e, "run": i} for i, e in enumerate([0.9, 0.3, 1.2, 0.5, 0.6])]
    row = _median_run(runs)
    assert row["run"] == 4 and row["ate_pct"] == 0.6  # the median of five
    assert row["ate_pct_runs"] == [0.9, 0.3, 1.2, 0.5, 0.6] and row["ate_pct_max"] == 1.2
    assert _median_run(runs[:2])["run"] == 1  # of two, the lower
    assert _median_run(runs[:1]) == runs[0]
    failed = [{"ate_pct": 0.4}, {"error": "only 3 of 20 frames registered in one model"}]
    assert _median_run(failed) == failed[1] | {"failed_runs": 1, "runs": 2}  # shown, not hidden
    assert _median_run([{"registered": 20}] * 3) == {"registered": 20}  # no truth: no error to rank by
