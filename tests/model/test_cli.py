"""``edmcgs train`` and ``edmcgs eval`` on a real HDF5 recording (events from the ESIM simulator)."""

import csv

import pytest

from edmcgs.cli import main
from edmcgs.model.checkpoint import load_checkpoint
from tests.support import tiny_scene
from tests.support.recordings import write_tiny_h5


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    return write_tiny_h5(tmp_path_factory.mktemp("rec") / "tiny.h5")


def test_train_then_eval(recording, tmp_path, capsys):
    ckpt = tmp_path / "tiny.ckpt"
    sets = ["init_points=500", "num_control_points=24", "deform_width=32", "deform_depth=2", "iterations=6",
            "substeps=4", "max_pair_steps=4", "eval_every=3", "eval_frames=1", "checkpoint_every=3",
            "train_scale=1.0"]
    args = ["train", str(recording), "-o", str(ckpt), "--quiet", "--history", str(tmp_path / "hist.csv")]
    assert main(args + [arg for s in sets for arg in ("--set", s)]) == 0
    model = load_checkpoint(ckpt)
    assert model.config.contrast_threshold == 0.2 and model.config.background == (0.1, 0.1, 0.1)
    assert model.meta.t_start_us == tiny_scene.T0 and model.meta.has_event_branch
    assert len((tmp_path / "hist.csv").read_text().splitlines()) == 3  # header + steps 3 and 6

    out_csv = tmp_path / "eval.csv"
    assert main(["eval", str(ckpt), str(recording), "--csv", str(out_csv)]) == 0
    rows = list(csv.DictReader(out_csv.open()))
    assert len(rows) == 2 and all(float(r["psnr"]) > 10 for r in rows)
    assert int(rows[0]["events"]) > 0
    printed = capsys.readouterr().out
    assert "| **mean** (2 frames)" in printed and "LPIPS (VGG) skipped" in printed

    # eval -q: the comparison with the baselines alone
    assert main(["eval", str(ckpt), str(recording), "-q"]) == 0
    quiet = capsys.readouterr().out
    assert "| **mean**" not in quiet and "| hold last anchor |" in quiet and "LPIPS" not in quiet

    # an existing checkpoint is replaced only with --force (and continued with --resume)
    before = ckpt.read_bytes()
    with pytest.raises(SystemExit) as exc:
        main(args)
    assert exc.value.code == 2 and "--force replaces it" in capsys.readouterr().err
    assert ckpt.read_bytes() == before

    # resume: two more iterations from the finished run
    resume = ["train", str(recording), "-o", str(ckpt), "--quiet", "--resume"]
    assert main([*resume, "--set", "iterations=8", "--set", "lambda_event=0.5"]) == 0
    for frozen in ("markov=false", "bg_layer=true", "init_points=10"):  # structure and initialisation
        before = ckpt.read_bytes()
        assert main([*resume, "--set", frozen]) == 1
        err = capsys.readouterr().err
        assert f"--resume cannot change ['{frozen.split('=')[0]}']" in err and "Traceback" not in err
        assert ckpt.read_bytes() == before


def test_eval_rejects_a_foreign_checkpoint(recording, tmp_path, capsys):
    bad = tmp_path / "bad.ckpt"
    bad.write_bytes(b"not a checkpoint")
    assert main(["eval", str(bad), str(recording)]) == 1
    assert "checkpoint" in capsys.readouterr().err


def test_resume_on_another_recording_fails_before_writing(recording, tmp_path, capsys):
    from edmcgs.model.checkpoint import save_checkpoint
    from tests.support.models import build

    other, _ = build(anchors_ms=(0, 80, 200))  # another split: other anchors
    ckpt = tmp_path / "other.ckpt"
    save_checkpoint(other, ckpt)
    before = ckpt.read_bytes()
    assert main(["train", str(recording), "-o", str(ckpt), "--quiet", "--resume",
                 "--set", "iterations=2"]) == 1
    err = capsys.readouterr().err
    assert "was not trained on this recording" in err and "Traceback" not in err
    assert ckpt.read_bytes() == before


def test_list_config_prints_every_key_by_part_with_its_value_and_description(capsys):
    import dataclasses

    from edmcgs.model.config import PARTS, EdmcgsConfig, preset

    assert main(["train", "--list-config", "--config", "real"]) == 0
    out = capsys.readouterr().out
    for f in dataclasses.fields(EdmcgsConfig):
        value = getattr(preset("real"), f.name)
        assert f"{f.name} = {value!r}\n    " in out, f.name
    assert "Use the event stream at all." in out  # the description written under the field
    headers = [out.index(f"# {part.__name__}") for part in PARTS]
    assert headers == sorted(headers) and "# Structure (frozen on --resume)" in out
    for part, start, end in zip(PARTS, headers, [*headers[1:], len(out)], strict=True):
        for f in dataclasses.fields(part):  # each key under its part's header
            assert start < out.index(f"\n{f.name} = ") < end, f.name
    with pytest.raises(SystemExit):
        main(["train"])
    assert "--list-config" in capsys.readouterr().err


def test_every_subcommand_answers_version(capsys):
    from edmcgs import __version__
    from edmcgs.cli import COMMANDS

    for command in COMMANDS:
        assert main([command, "--version"]) == 0
        assert capsys.readouterr().out == f"edmcgs {__version__}\n"
