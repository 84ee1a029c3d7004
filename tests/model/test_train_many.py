"""``edmcgs train`` over several recordings: one checkpoint each in the output folder, one after
another (``--ray``: side by side as Ray tasks, in ``test_train_ray_e2e.py``)."""

from __future__ import annotations

import pytest

from edmcgs.cli import main
from edmcgs.model.checkpoint import load_checkpoint
from harness.server import build_scene

TINY = ["init_points=300", "num_control_points=16", "deform_width=16", "deform_depth=2", "iterations=2",
        "substeps=2", "max_pair_steps=2", "eval_every=0", "checkpoint_every=0", "train_scale=1.0"]


@pytest.fixture(scope="module")
def recordings(tmp_path_factory):
    out = []
    for name, seed in (("east", 1), ("west", 2)):
        folder = tmp_path_factory.mktemp(name)
        rec, _ = build_scene(folder, width=48, height=32, duration_s=0.6, event_rate=5_000, init_points=300,
                             control_points=16, seed=seed)
        out.append(rec.rename(folder / f"{name}.h5"))
    return out


def train_args(recordings, out, *extra) -> list[str]:
    return ["train", *map(str, recordings), "-o", str(out), "--quiet", *extra,
            *[a for s in TINY for a in ("--set", s)]]


def test_several_recordings_train_into_one_folder(recordings, tmp_path, capsys):
    out = tmp_path / "models"
    assert main(train_args(recordings, out)) == 0
    for rec in recordings:
        model = load_checkpoint(out / f"{rec.stem}.ckpt")
        assert model.meta.event_width == 48
    printed = capsys.readouterr().out
    assert f"{recordings[0]}: wrote {out / 'east.ckpt'}" in printed
    # Again into the same folder: refused without --force or --resume, as one checkpoint is.
    assert main(train_args(recordings, out)) == 1
    assert "east.ckpt" in capsys.readouterr().err
    assert main(train_args(recordings, out, "--force")) == 0


def test_several_recordings_refuse_what_would_clash(recordings, tmp_path, capsys):
    file = tmp_path / "a.ckpt"
    file.write_bytes(b"x")
    assert main(train_args(recordings, file)) == 1
    assert "-o is a folder" in capsys.readouterr().err
    assert main(train_args([recordings[0], recordings[0]], tmp_path / "m")) == 1
    assert "share the name east" in capsys.readouterr().err
    assert main(train_args(recordings, tmp_path / "m", "--history", str(tmp_path / "h.csv"))) == 1
    assert "--history takes one recording" in capsys.readouterr().err
    assert main(train_args(recordings, tmp_path / "m", "--resume", str(file))) == 1
    assert "--resume CKPT takes one recording" in capsys.readouterr().err


def test_each_run_has_its_own_resume_hint_and_curves(recordings):
    import argparse

    from edmcgs.train_cli import _shared_argv

    argv = [str(recordings[0]), str(recordings[1]), "-o", "out", "--ray", "--ray-cpus", "2", "--threads", "2",
            "--tensorboard=tb", "--set", "iterations=4"]
    args = argparse.Namespace(argv=argv, recording=[str(r) for r in recordings])
    assert _shared_argv(args) == ["--threads", "2", "--set", "iterations=4"]
