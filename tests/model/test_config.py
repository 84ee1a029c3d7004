"""The config in parts: structure and initialisation (frozen on resume), losses, schedule; read flat."""

from dataclasses import fields

import pytest
import torch

from edmcgs.errors import InvalidInputError
from edmcgs.model.checkpoint import checksum, load_checkpoint, read_checkpoint
from edmcgs.model.config import (
    FROZEN_ON_RESUME,
    FROZEN_PARTS,
    PARTS,
    EdmcgsConfig,
    Initialisation,
    Losses,
    Schedule,
    Structure,
    field_docs,
    preset,
)
from edmcgs.server import demo
from tests.support.models import TINY, build


def _shapes(model) -> dict:
    return {name: tuple(t.shape) for name, t in model.state_dict().items()}


def _other(value):
    """A valid value other than ``value`` (halved fractions stay in range)."""
    if isinstance(value, bool):
        return not value
    if isinstance(value, int):
        return value + 1
    if isinstance(value, float):
        return value * 0.5 if value else 0.5
    return tuple(v * 0.5 for v in value)


def test_the_parts_partition_the_config_and_read_flat():
    names = [f.name for part in PARTS for f in fields(part)]
    assert len(names) == len(set(names)), "a field in two parts"
    assert names == [f.name for f in fields(EdmcgsConfig)]  # structure first, schedule last
    assert list(preset("real").to_dict()) == names
    cfg = preset("demo")
    assert all(isinstance(cfg, part) for part in PARTS)
    assert (cfg.deform_width, cfg.init_points, cfg.lambda_event, cfg.iterations) == (128, 3000, 1.0, 1500)
    assert cfg.replace(skin_k=2).skin_k == 2 and cfg.with_overrides(["lr_event=0.5"]).lr_event == 0.5
    docs = field_docs()
    assert set(docs) == set(names) and all(docs.values())
    assert docs["skin_k"].startswith("K: control points each Gaussian is bound to")
    assert all(part.__doc__ for part in PARTS)


def test_frozen_on_resume_is_derived_from_the_parts_that_describe_the_tensors():
    assert FROZEN_PARTS == (Structure, Initialisation)
    assert FROZEN_ON_RESUME == tuple(f.name for part in FROZEN_PARTS for f in fields(part))
    cfg = preset("demo")
    assert cfg.frozen_changes(cfg.with_overrides(["iterations=9", "lambda_event=0.1", "tli=false"])) == []
    resumed = cfg.with_overrides(["init_points=10", "bg_layer=true", "event_pool=2"])
    assert cfg.frozen_changes(resumed) == ["event_pool", "bg_layer", "init_points"]


def test_losses_and_schedule_leave_the_tensors_as_they_are():
    base, _ = build()
    changed = TINY.replace(**{f.name: _other(getattr(TINY, f.name))
                              for part in (Losses, Schedule) for f in fields(part)})
    assert all(getattr(changed, f.name) != getattr(TINY, f.name) for part in (Losses, Schedule)
               for f in fields(part))
    model, _ = build(changed)
    assert _shapes(model) == _shapes(base)


@pytest.mark.parametrize("change", [{"markov": False}, {"bg_layer": True}, {"anchor_windows": True},
                                    {"skin_k": 2}, {"event_hidden": 16}, {"deform_depth": 3}])
def test_a_structure_field_changes_which_tensors_there_are(change):
    assert set(change) <= {f.name for f in fields(Structure)}
    base, _ = build()
    model, _ = build(TINY.replace(**change))
    assert _shapes(model) != _shapes(base)


LATER_FIELDS = ("anchor_windows", "bg_layer", "dynamic_threshold", "event_act", "init_opacity", "lambda_next",
                "lr_background", "next_levels")
"""Config fields the checkpoints written before them lack (the demo bundled until schema version 3)."""


def test_an_old_flat_checkpoint_config_loads(tmp_path):
    # An older checkpoint stores its config as one flat map without the fields added since.
    payload = read_checkpoint(demo.files()[0])
    stored = {k: v for k, v in payload["meta"]["config"].items() if k not in LATER_FIELDS}
    payload["meta"]["config"] = stored
    payload["checksum"] = checksum(payload)
    torch.save(payload, tmp_path / "old.ckpt")
    names = {f.name for f in fields(EdmcgsConfig)}
    assert set(stored) < names and "bg_layer" not in stored
    config = load_checkpoint(tmp_path / "old.ckpt").config
    assert {k: v for k, v in config.to_dict().items() if k in stored} == stored
    assert config.bg_layer is False and config.event_act == "relu"  # the defaults of the missing fields
    with pytest.raises(InvalidInputError, match="unknown keys"):
        EdmcgsConfig.from_dict({**stored, "from_a_newer_writer": 1})


def test_a_mistyped_key_or_preset_names_the_closest_ones():
    cfg = preset("demo")
    with pytest.raises(InvalidInputError) as info:
        cfg.with_overrides(["iteration=50"])
    assert "did you mean 'iterations'?" in str(info.value) and "init_points" not in str(info.value)
    with pytest.raises(InvalidInputError) as info:
        cfg.with_overrides(["zzzz=1"])
    assert "did you mean" not in str(info.value) and "--list-config" in str(info.value)
    with pytest.raises(InvalidInputError, match="did you mean 'demo'"):
        preset("dmeo")


def test_an_unknown_command_names_the_closest_one(capsys):
    from edmcgs.cli import main

    with pytest.raises(SystemExit) as exc:
        main(["trian"])
    assert exc.value.code == 2 and "did you mean 'train'?" in capsys.readouterr().err
