"""The street3d benchmark: the `moving` preset on a handheld camera in a 3D street, with estimated poses.

    .venv/bin/python -m bench.street3d [--size full|small] [--seconds S] [--steps N] [--seed K]
        [--variants ...]

1. Builds the street (``edmcgs synth street3d --size SIZE --seconds S --seed 0``: a handheld DAVIS346
   walking along a ray-cast street, cars driving both ways; 25 Hz grey APS frames with exposure blur and
   read noise, DAVIS346-like events; every fifth frame an anchor, the others held out; a second camera's
   frames at the held-out times, the novel views), or takes ``--recording``.
2. Estimates the poses as a user would: ``edmcgs record REC --poses auto -o REC_auto.h5`` (structure from
   motion over every frame: the trajectory, the 3D points, the novel views carried into its frame),
   timed; the trajectory error after a Sim(3) alignment to the true poses (evo).
3. The true-pose twin of the same run: REC itself (its true poses) with the same structure-from-motion
   points, carried into the true frame by the similarity between the estimated and the true poses of
   the frames (``geometry.Similarity.fit_poses``): the runs then differ in their poses alone.
4. Trains each variant with ``edmcgs train REC --config moving [--set ...]`` in its own process, one
   torch thread (``bench.traffic.train``: wall time, CPU time, peak memory; cached).
5. Scores every checkpoint on the held-out frames through the inference path, beside the trivial
   baselines (hold the last anchor, blend the neighbouring anchors, integrate the events onto the last
   anchor): PSNR, SSIM, and PSNR over the moving pixels (where the ray caster's frame shows a car, widened
   by 2 pixels for the exposure's blur); and on the novel views (no baseline can make them) beside
   ``events=false``.

Writes ``street3d.md``, ``street3d.json`` and ``street3d_frames.png`` (held-out frames and novel views:
truth, variants, baselines) into ``--out``; recordings and checkpoints are cached in ``--cache``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from bench.results import meets, pick_variants, table, variant_parser, write_json
from bench.traffic import _edmcgs, measured_run, train

PRESET = "moving"
VARIANTS = {"full": ("auto", []), "true poses": ("true", []), "events=false": ("auto", ["events=false"])}
"""name -> (which recording: the estimated poses or the true ones, --set overrides)."""
CAR_MARGIN = 2
"""Pixels by which the cars' mask is widened (the exposure's blur reaches past their sharp outline)."""
TARGETS = {
    "auto_vs_true_db": ("<=", 0.5),
    "full_minus_best_baseline_db": (">=", 1.0),
    "full_minus_events_false_db": (">=", 2.0),
    "ate_pct": ("<=", 1.0),
}


# ------------------------------------------------------------------------------- recordings

def scene_args(size: str, seconds: float) -> list[str]:
    return ["--size", size, "--seconds", f"{seconds:g}", "--seed", "0"]


def build_scene(cache: Path, args: list[str]) -> Path:
    path = cache / f"street3d_{'_'.join(a.lstrip('-') for a in args)}.h5"
    if not path.exists():
        cache.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".partial.h5")
        measured_run([*_edmcgs(), "synth", "street3d", *args, "-q", "-o", str(tmp)], cache / "build.log")
        tmp.replace(path)
    return path


def estimate(rec: Path) -> tuple[Path, dict]:
    """``edmcgs record REC --poses auto`` (cached): the recording with the estimated poses, and what it
    cost (measured when it ran)."""
    out = rec.with_name(rec.stem + "_auto.h5")
    cost = rec.with_name(rec.stem + "_auto.json")
    if not (out.exists() and cost.exists()):
        cmd = [*_edmcgs(), "record", str(rec), "--poses", "auto", "-q", "--force", "-o", str(out)]
        usage = measured_run(cmd, rec.with_name(rec.stem + "_auto.log"))
        cost.write_text(json.dumps(usage))
    return out, json.loads(cost.read_text())


def pose_accuracy(truth_rec, est):
    """(the similarity carrying ``est``'s estimated world onto ``truth_rec``'s true one, the pose
    accuracy: {registered, frames, ate_m, path_m, ate_pct, points, scale, seconds}) of two recordings
    read whole (``read_recording``)."""
    from edmcgs.geometry import Similarity
    from edmcgs.pipeline import all_frames
    from harness.pose_scenes import trajectory_error

    frames = all_frames(truth_rec)
    truth = frames.poses[np.searchsorted(frames.t_us, est.trajectory_t_us)]
    to_true = Similarity.fit_poses(est.trajectory_c2w, truth)
    rmse, length = trajectory_error(est.trajectory_t_us, est.trajectory_c2w, truth)
    return to_true, {"registered": len(est.trajectory_t_us), "frames": len(frames), "ate_m": rmse,
                     "path_m": length, "ate_pct": 100.0 * rmse / length, "points": len(est.points_xyz),
                     "scale": to_true.scale, "seconds": est.metadata["poses"]["seconds"]}


def true_twin(rec: Path, auto: Path) -> tuple[Path, dict]:
    """REC with the structure-from-motion points of ``auto`` carried into REC's true frame (cached), and
    the pose accuracy (``pose_accuracy``)."""
    from edmcgs.sensor.files.recording import read_recording, write_recording

    truth_rec, est = read_recording(rec), read_recording(auto)
    to_true, accuracy = pose_accuracy(truth_rec, est)
    out = rec.with_name(rec.stem + "_true.h5")
    if not out.exists() or out.stat().st_mtime < auto.stat().st_mtime:
        write_recording(out, replace(truth_rec, points_xyz=to_true.points(est.points_xyz),
                                     points_colors=est.points_colors))
    return out, accuracy


# ------------------------------------------------------------------------------- scores

def _scene(rec):
    from edmcgs.synth.street3d import StreetScene

    return StreetScene(rec.width, rec.height, seed=int(rec.metadata["seed"]),
                       occupancy=float(rec.metadata.get("occupancy", 0.8)))


def car_mask(scene, t_us: int, c2w: np.ndarray) -> np.ndarray:
    """[H, W] bool: where the ray caster's frame at ``t_us`` from ``c2w`` (true frame) shows a moving car,
    widened by ``CAR_MARGIN`` pixels."""
    mask, m = scene.car_pixels(t_us * 1e-6, c2w), CAR_MARGIN
    h, w = mask.shape
    padded = np.pad(mask, m)  # a square dilation that stops at the frame's edges
    shifts = [padded[dy:dy + h, dx:dx + w] for dy in range(2 * m + 1) for dx in range(2 * m + 1)]
    return np.any(shifts, axis=0)


class Scores:
    """Running PSNR, SSIM and moving-pixel squared error per name."""

    def __init__(self):
        self.acc: dict[str, dict] = {}

    def add(self, name: str, image: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> None:
        from edmcgs.model.eval.metrics import psnr, ssim_score

        a = self.acc.setdefault(name, {"psnr": [], "ssim": [], "sq": 0.0, "px": 0})
        a["psnr"].append(psnr(image, truth))
        a["ssim"].append(ssim_score(image, truth))
        a["sq"] += float(((image - truth) ** 2)[mask].sum())
        a["px"] += int(mask.sum()) * image.shape[-1]

    def summary(self) -> dict[str, dict]:
        return {name: {"psnr": float(np.mean(a["psnr"])), "ssim": float(np.mean(a["ssim"])),
                       "moving_psnr": float(10 * np.log10(1.0 / max(a["sq"] / max(a["px"], 1), 1e-12))),
                       "frames": len(a["psnr"])} for name, a in self.acc.items()}


def score(datas: dict, models: dict, novel: dict, scene, truth_poses) -> tuple[dict, dict, float]:
    """(held-out scores of every model and baseline, novel-view scores of every model, the moving
    fraction of the held-out pixels). ``datas``/``novel``: each model's training data and novel views
    (in its own world frame); ``truth_poses``: (held-out c2w, novel c2w) in the true frame, for the masks."""
    from edmcgs.model.eval.baselines import BASELINES, baseline_image
    from edmcgs.model.eval.evaluation import render_held_out

    held, views = Scores(), Scores()
    first = next(iter(datas.values()))
    moving = 0
    for i in first.evaluable().tolist():
        t = int(first.held_out_t_us[i])
        truth = first.held_out_images[i].astype(np.float32) / 255.0
        mask = car_mask(scene, t, truth_poses[0][i])
        moving += int(mask.sum())
        for name in BASELINES:
            held.add(name, baseline_image(first, t, name)[0], truth, mask)
        for name, m in models.items():
            held.add(name, render_held_out(m, datas[name], i)[0], truth, mask)
    for k, t in enumerate(next(iter(novel.values())).t_us.tolist()):
        mask = car_mask(scene, t, truth_poses[1][k])
        for name, m in models.items():
            frames, data = novel[name], datas[name]
            if not first.anchors_t_us[0] <= t <= first.t_end_us:
                continue
            image = render_view(m, data, t, frames.poses[k])
            views.add(name, image, frames.images[k].astype(np.float32) / 255.0, mask)
    size = first.held_out_images.shape[1] * first.held_out_images.shape[2]
    return held.summary(), views.summary(), moving / max(len(first.evaluable()) * size, 1)


def render_view(model, data, t_us: int, c2w: np.ndarray) -> np.ndarray:
    """The model at ``t_us`` (moved by the events since its anchor) seen from another camera ``c2w``."""
    tau = model.tau(t_us)
    emap = data.event_map(tau, t_us) if data.event_map is not None and t_us > tau else None
    state = model.deform(t_us, emap, data.trajectory.at(t_us))
    return model.render(state, c2w, model.meta.intrinsics)


# ------------------------------------------------------------------------------- the report

def pick_frames(data, scene, truth_poses, count: int = 2) -> list[int]:
    """Held-out frames farthest from their anchor showing the most car pixels, from different gaps."""
    idx = data.evaluable()
    gap = np.searchsorted(data.anchors_t_us, data.held_out_t_us[idx], side="right") - 1
    since = data.held_out_t_us[idx] - data.anchors_t_us[gap]
    far = idx[since >= np.sort(since)[len(since) // 2]]
    cars = {int(i): int(car_mask(scene, int(data.held_out_t_us[i]), truth_poses[i]).sum()) for i in far}
    picked, gaps = [], set()
    for i in sorted(cars, key=cars.get, reverse=True):
        g = int(np.searchsorted(data.anchors_t_us, data.held_out_t_us[i], side="right"))
        if g not in gaps:
            picked.append(i)
            gaps.add(g)
        if len(picked) == count:
            break
    return picked


def frames_figure(datas: dict, models: dict, novel: dict, picked: list[int], path: Path) -> None:
    """Rows: the picked held-out frames (truth, variants, baselines), then the novel views at the same
    times (truth, variants)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from edmcgs.model.eval.baselines import BASELINES, baseline_image
    from edmcgs.model.eval.evaluation import render_held_out

    first = next(iter(datas.values()))
    t0 = int(first.anchors_t_us[0])
    rows = []
    for i in picked:
        t = int(first.held_out_t_us[i])
        since = (t - int(first.anchors_t_us[np.searchsorted(first.anchors_t_us, t, side="right") - 1])) / 1e3
        label = f"t = {(t - t0) / 1e3:.0f} ms ({since:.0f} ms after its anchor)"
        row = [(f"held-out truth, {label}", first.held_out_images[i].astype(np.float32) / 255.0)]
        row += [(name, render_held_out(m, datas[name], i)[0]) for name, m in models.items()]
        row += [(name, baseline_image(first, t, name)[0]) for name in BASELINES]
        rows.append(row)
    for i in picked:
        t = int(first.held_out_t_us[i])
        k = int(np.searchsorted(next(iter(novel.values())).t_us, t))
        truth = next(iter(novel.values())).images[k] / 255.0
        row = [(f"novel view truth, t = {(t - t0) / 1e3:.0f} ms", truth)]
        row += [(f"{name}: novel view", render_view(m, datas[name], t, novel[name].poses[k]))
                for name, m in models.items()]
        rows.append(row)
    cols = max(len(r) for r in rows)
    h, w = first.held_out_images.shape[1:3]
    fig, axes = plt.subplots(len(rows), cols, figsize=(2.9 * cols, 2.9 * h / w * len(rows) + 0.4),
                             squeeze=False)
    for r, row in enumerate(rows):
        for c in range(cols):
            ax = axes[r, c]
            ax.axis("off")
            if c < len(row):
                name, image = row[c]
                ax.imshow(np.clip(np.asarray(image)[..., 0], 0, 1), cmap="gray", vmin=0, vmax=1,
                          interpolation="nearest")
                ax.set_title(name, fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def markdown(r: dict, command: str) -> str:
    runs = {run["name"]: run for run in r["runs"]}
    pa = r["poses"]
    lines = ["# street3d benchmark: the `moving` preset on a handheld camera, with estimated poses", "",
             f"`{command}` on {r['machine']}. The scene: {r['scene']}; {r['anchors']} anchors, "
             f"{r['frames']} held-out frames and {r['novel_frames']} novel views scored. One training "
             f"seed ({r['seed']}).", "",
             "## Poses", "",
             "`edmcgs record REC --poses auto` (structure from motion over every frame): "
             f"{pa['registered']} of {pa['frames']} frames registered, {pa['points']} points, absolute "
             f"trajectory error {pa['ate_m'] * 100:.1f} cm = {pa['ate_pct']:.2f} % of the "
             f"{pa['path_m']:.2f} m path after a Sim(3) alignment (evo); {pa['seconds']:.0f} s of structure "
             "from motion "
             f"({r['pose_cost']['wall_s']:.0f} s wall for the command). The true-pose run is trained on the "
             "recording's own poses with the same points, carried into its frame by the similarity between "
             "the estimated and the true poses (`Similarity.fit_poses`).", "",
             "## Held-out frames", "",
             "| held-out frames | PSNR (dB) | SSIM | PSNR on the cars' pixels | train wall | train CPU "
             "| peak memory |", "|---|---|---|---|---|---|---|"]

    def label(name):
        if name not in runs:
            return f"{name} (no model)"
        kind, sets = VARIANTS[name]
        poses = "true poses" if kind == "true" else "`--poses auto`"
        return f"{'full model' if not sets else '`--set ' + ' '.join(sets) + '`'} ({poses})"

    def cost(name):
        run = runs.get(name)
        return (f"{run['wall_s'] / 60:.1f} min | {run['cpu_s'] / 60:.1f} min | {run['peak_gb']:.2f} GB"
                if run else "— | — | —")

    for name, row in r["scores"].items():
        lines.append(f"| {label(name)} | {row['psnr']:.2f} | {row['ssim']:.3f} | {row['moving_psnr']:.2f} "
                     f"| {cost(name)} |")
    lines += ["", "## Novel views (the rig's second camera, 0.3 m to the left, turned 5 degrees)", "",
              "| novel views | PSNR (dB) | SSIM | PSNR on the cars' pixels |", "|---|---|---|---|"]
    for name, row in r["novel"].items():
        lines.append(f"| {label(name)} | {row['psnr']:.2f} | {row['ssim']:.3f} | {row['moving_psnr']:.2f} |")
    lines += ["", "The cars' pixels: where the ray caster's frame at that time shows a moving car, widened "
              f"by {CAR_MARGIN} pixels ({100 * r['moving_fraction']:.1f} % of the held-out pixels). "
              f"Training: `edmcgs train REC --config {PRESET} --threads 1`, each variant in its own "
              "process (wall time includes its periodic evaluations).", "",
              "```", table(r["summary"], TARGETS), "```", "",
              "Commands (what the benchmark runs, cached in `--cache`):", "", "```",
              *r["commands"], "```", "", "![held-out frames and novel views](street3d_frames.png)", ""]
    return "\n".join(lines)


def _parser() -> argparse.ArgumentParser:
    p = variant_parser("street3d", __doc__, VARIANTS, "a street3d recording instead of building one")
    p.add_argument("--size", choices=("full", "small"), default="full", help="the street's size")
    p.add_argument("--seconds", type=float, default=4.0, help="the street's length in time")
    p.add_argument("--seed", type=int, default=0, help="the trainings' seed (--set seed=K; the street "
                                                       "and its poses stay the same)")
    return p


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    names = pick_variants(args.variants, VARIANTS, "bench.street3d")
    import torch

    from edmcgs.model.checkpoint import load_checkpoint
    from edmcgs.model.eval.baselines import BASELINES
    from edmcgs.pipeline import all_frames, open_recording, training_data
    torch.set_num_threads(1)

    scene = scene_args(args.size, args.seconds)
    rec_path = args.recording or build_scene(args.cache, scene)
    auto_path, pose_cost = estimate(rec_path)
    true_path, accuracy = true_twin(rec_path, auto_path)
    paths = {"auto": auto_path, "true": true_path}
    sets = ([] if args.steps is None else [f"iterations={args.steps}"]) + \
        ([f"seed={args.seed}"] if args.seed else [])  # every variant's --set, before its own
    runs = [train(paths[VARIANTS[n][0]], n, sets + VARIANTS[n][1], args.cache, PRESET) for n in names]
    recs = {kind: open_recording(path) for kind, path in paths.items()}
    datas = {n: training_data(recs[VARIANTS[n][0]]) for n in names}
    novel = {n: recs[VARIANTS[n][0]].novel_views for n in names}
    models = {run["name"]: load_checkpoint(args.cache / run["checkpoint"]) for run in runs}
    truth = recs["true"]
    frames = all_frames(truth)
    first = next(iter(datas.values()))
    truth_poses = (frames.poses[np.searchsorted(frames.t_us, first.held_out_t_us)], truth.novel_views.poses)
    street = _scene(truth)
    held, views, moving = score(datas, models, novel, street, truth_poses)
    baselines = {k: v for k, v in held.items() if k not in models}
    held = {k: held[k] for k in [*models, *baselines]}
    summary: dict = {"ate_pct": accuracy["ate_pct"]}
    if "full" in models:
        best = max(BASELINES, key=lambda b: held[b]["psnr"])
        summary |= {"full_psnr": held["full"]["psnr"], "best_baseline_psnr": held[best]["psnr"],
                    "full_minus_best_baseline_db": held["full"]["psnr"] - held[best]["psnr"],
                    "full_moving_psnr": held["full"]["moving_psnr"]}
        if "true poses" in models:
            summary["auto_vs_true_db"] = abs(held["full"]["psnr"] - held["true poses"]["psnr"])
        if "events=false" in models:
            summary["full_minus_events_false_db"] = held["full"]["psnr"] - held["events=false"]["psnr"]
            summary["novel_full_minus_events_false_db"] = (views["full"]["psnr"]
                                                           - views["events=false"]["psnr"])
    described = (f"`{rec_path}`" if args.recording else
                 f"`edmcgs synth street3d {' '.join(scene)}` (ray-cast, not Gaussians; "
                 f"{first.intrinsics.width}x{first.intrinsics.height} grey, exposure blur, read noise, "
                 "DAVIS346-like events; a handheld camera walking 0.9 m/s, cars at 7-10 m/s; anchors at "
                 "5 fps)")
    commands = ([] if args.recording else [f"edmcgs synth street3d {' '.join(scene)} -o street.h5"]) + [
        "edmcgs record street.h5 --poses auto -o street_auto.h5",
        *[f"edmcgs train {'street_auto.h5' if VARIANTS[n][0] == 'auto' else 'street_true.h5'} "
          f"--config {PRESET} --threads 1" + "".join(f" --set {o}" for o in sets + VARIANTS[n][1])
          + f" -o {n.replace(' ', '_').replace('=', '_')}.ckpt" for n in names]]
    r = {"machine": f"{platform.machine()}, {os.cpu_count()} CPUs", "recording": str(rec_path),
         "scene": described, "anchors": len(first.anchors_t_us), "frames": len(first.evaluable()),
         "novel_frames": next(iter(views.values()))["frames"] if views else 0, "moving_fraction": moving,
         "poses": accuracy, "pose_cost": pose_cost, "runs": runs, "scores": held, "novel": views,
         "summary": summary, "commands": commands, "seed": args.seed}
    r["targets_met"] = {k: meets(v, TARGETS[k]) for k, v in summary.items() if k in TARGETS}
    args.out.mkdir(parents=True, exist_ok=True)
    picked = pick_frames(first, street, truth_poses[0])
    frames_figure(datas, models, novel, picked, args.out / "street3d_frames.png")
    command = "python -m bench.street3d" + (f" {' '.join(argv)}" if argv else "")
    (args.out / "street3d.md").write_text(markdown(r, command))
    write_json(args.out / "street3d.json", r)
    write_json(args.json, r)
    print(table(summary, TARGETS))
    print(f"wrote {args.out / 'street3d.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
