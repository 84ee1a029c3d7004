"""bench.traffic end to end on a short, small street: each variant trained by the real CLI in its own
process and measured, scored beside the baselines on the same frames, the lean and split sections, and
the cache that keeps a second run from training again."""

import json

import numpy as np

from bench import traffic
from edmcgs.model.eval.baselines import BASELINES, score_baselines
from edmcgs.pipeline import open_recording, training_data
from edmcgs.sensor.files.recording import write_recording
from edmcgs.synth.traffic_build import TrafficConfig, build_traffic


def test_trains_measures_and_scores_beside_the_baselines(tmp_path):
    rec_path = tmp_path / "street.h5"
    write_recording(rec_path, build_traffic(TrafficConfig(width=173, height=130, duration_s=0.8, fps=5.0),
                                            progress=False))
    out, cache = tmp_path / "out", tmp_path / "cache"
    argv = ["--recording", str(rec_path), "--steps", "2", "--variants", "full,bg_layer=false",
            "--out", str(out), "--cache", str(cache)]
    assert traffic.main(argv) == 0
    r = json.loads((out / "traffic.json").read_text())

    data = training_data(open_recording(rec_path))
    frames = len(data.evaluable())
    assert r["frames"] == frames > 0
    for run in r["runs"]:  # the training process itself was measured
        assert run["wall_s"] > 0 and run["cpu_s"] > 0 and 0.1 < run["peak_gb"] < 20
    names = {"full", "bg_layer=false", *BASELINES, traffic.MEDIAN}
    assert set(r["scores"]) == names
    for row in r["scores"].values():
        assert row["frames"] == frames and all(np.isfinite(row[k]) for k in ("psnr", "ssim", "moving_psnr"))
    # the baselines are the ones every other command reports, on the same frames
    for name, rows in score_baselines(data).items():
        assert abs(r["scores"][name]["psnr"] - np.mean([s.psnr for s in rows])) < 1e-9
    s = r["summary"]
    assert abs(s["full_minus_blend_db"] - (r["scores"]["full"]["psnr"]
                                           - r["scores"]["blend of neighbouring anchors"]["psnr"])) < 1e-9
    assert abs(s["train_minutes"] - r["runs"][0]["wall_s"] / 60) < 1e-9
    assert r["lean"]["within_threshold"]
    assert r["split"]["gaussians"][0] < r["split"]["gaussians"][1]  # the layer holds the static street
    text = (out / "traffic.md").read_text()
    for label in ("full model", "`--set bg_layer=false`", "hold last anchor (no model)",
                  "median of the anchors"):
        assert label in text
    assert (out / "traffic_frames.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    # a second run reuses every trained checkpoint and its measured cost
    assert traffic.main(argv) == 0
    again = json.loads((out / "traffic.json").read_text())
    assert all(run["cached"] for run in again["runs"])
    assert [run["wall_s"] for run in again["runs"]] == [run["wall_s"] for run in r["runs"]]
