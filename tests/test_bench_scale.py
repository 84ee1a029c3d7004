"""bench.scale's summary and page with a length repeated (``--lengths 3,60,3``): each run is a row, and the
60 s / 3 s ratios take the mean of the 3 s runs."""

from bench import scale


def _row(cpu_per_s: float, render_ms: float | None = None) -> dict:
    row = {"anchors": 16, "events": 2e6, "steps": 1500, "cpu_per_s": cpu_per_s, "margin_db": 1.5}
    return row if render_ms is None else row | {"render_p50_ms": render_ms}


def test_a_repeated_length_is_its_own_row_and_the_ratio_takes_the_mean_of_its_runs():
    rows = {"3": _row(50.0, 10.0), "60": _row(66.0, 12.0), "3#2": _row(60.0)}
    results = {"machine": "test", "size": "full", "scenes": {"traffic": rows}}
    summary = results["summary"] = scale.summarise(results)
    assert summary["traffic_cpu_per_s_ratio_60_3"] == 66.0 / 55.0
    assert summary["traffic_render_p50_ratio_60_3"] == 12.0 / 10.0  # served: the first run alone
    page = scale.markdown(results, "python -m bench.scale --lengths 3,60,3")
    table = [line for line in page.splitlines() if line.startswith("| 3 s") or line.startswith("| 60 s")]
    assert [line.split(" | ")[0] for line in table] == ["| 3 s", "| 3 s, run 2", "| 60 s"]


def test_the_handheld_street_trains_with_the_moving_preset_and_lists_its_estimated_poses():
    poses = {"registered": 76, "frames": 76, "ate_pct": 0.12, "wall_s": 40.0, "cpu_s": 70.0, "peak_gb": 0.5}
    rows = {"3": _row(60.0) | {"poses": poses}, "10": _row(70.0) | {"poses": poses | {"frames": 251}}}
    results = {"machine": "test", "size": "full", "scenes": {"street3d": rows, "traffic": {"3": _row(50.0)}}}
    results["summary"] = scale.summarise(results)
    page = scale.markdown(results, "python -m bench.scale --scenes street3d,traffic --lengths 3,10")
    street, traffic = page.split("## street3d")[1].split("## traffic")
    assert "`--config moving`, 75 steps per span" in street and "--poses auto" in street
    assert "| 10 s | 76 of 251 | 0.12 % | 40 s | 70 s |" in street
    assert "`--config real`, 100 steps per span" in traffic and "--poses auto" not in traffic


def test_a_length_posed_but_not_trained_leaves_the_ratios_to_the_trained_ones():
    poses = {"registered": 1501, "frames": 1501, "ate_pct": 0.02, "wall_s": 900.0, "cpu_s": 1600.0}
    untrained = {"anchors": 301, "events": 8e7, "poses": poses}
    trained = {"wall_min": 20.0, "peak_gb": 1.0}
    rows = {"3": _row(60.0) | trained, "10": _row(66.0) | trained | {"peak_gb": 2.0}, "60": untrained}
    results = {"machine": "test", "size": "full", "scenes": {"street3d": rows}}
    summary = results["summary"] = scale.summarise(results)
    assert summary["street3d_cpu_per_s_ratio_10_3"] == 66.0 / 60.0
    assert summary["street3d_train_peak_gb_10"] == 2.0
    page = scale.markdown(results, "python -m bench.scale --scenes street3d --lengths 3,10,60")
    assert "| 60 s | 1501 of 1501 | 0.02 % | 900 s | 1600 s |" in page and "Not trained yet: 60 s" in page


def test_a_training_interrupted_mid_run_is_continued_with_its_time_before_counted(tmp_path, monkeypatch):
    from edmcgs.model.checkpoint import save_checkpoint
    from tests.support.models import build

    model, _ = build()
    commands = []

    def run(cmd, log):
        commands.append(cmd)
        return {"wall_s": 10.0, "cpu_s": 9.0, "peak_gb": 0.1}

    monkeypatch.setattr(scale, "measured_run", run)
    monkeypatch.setattr(scale, "run_key", lambda *a: "k")
    save_checkpoint(model, tmp_path / "k.ckpt", train_state={"step": 400, "train_seconds": 100.0})
    done = scale.train(tmp_path / "rec.h5", tmp_path, preset="moving")
    assert "--resume" in commands[0] and "--force" not in commands[0]
    assert (done["resumed_at"], done["wall_s"], done["cpu_s"]) == (400, 110.0, 109.0)
    # a final checkpoint (nothing to continue) trains afresh
    (tmp_path / "k.json").unlink()
    save_checkpoint(model, tmp_path / "k.ckpt")
    again = scale.train(tmp_path / "rec.h5", tmp_path, preset="moving")
    assert "--force" in commands[1] and again["resumed_at"] is None and again["cpu_s"] == 9.0
