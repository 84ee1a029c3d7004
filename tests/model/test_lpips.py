"""LPIPS on user-provided weights: equal to the reference ``lpips`` package, clear when weights are absent."""

import numpy as np
import pytest
import torch

from edmcgs.errors import InvalidInputError
from edmcgs.model.eval.lpips import LPIPS, find_weights, missing_weights
from tests.support.lpips_weights import image_pair, random_weights

# The reference package (lpips 0.1.4, torchvision's vgg16 layout) on random_weights(0) and image_pair(1),
# inputs in [0, 1] (normalize=True); the last value is the first pair averaged to grey.
REFERENCE = [0.012203233316540718, 0.012146105989813805, 0.0]
REFERENCE_GREY = 0.01119285263121128


@pytest.fixture(scope="module")
def metric():
    return LPIPS(*random_weights(0))


def test_matches_the_reference_implementation(metric):
    a, b = image_pair(1)
    np.testing.assert_allclose(metric(a, b).double().numpy(), REFERENCE, rtol=1e-5, atol=1e-9)


def test_grey_images_are_compared_as_rgb(metric):
    a, b = image_pair(1)
    grey = [x[0].mean(0, keepdim=True).permute(1, 2, 0).numpy() for x in (a, b)]  # [H, W, 1]
    assert metric.score(*grey) == pytest.approx(REFERENCE_GREY, rel=1e-5)


def test_identical_images_score_zero_and_extremes_stay_finite(metric):
    white, black = np.ones((40, 52, 3), np.float32), np.zeros((40, 52, 3), np.float32)
    assert metric.score(white, white) == 0.0
    far = metric.score(white, black)
    assert np.isfinite(far) and far > 0


def test_load_reads_files_and_names_what_is_wrong(tmp_path):
    vgg, lin = random_weights(0)
    torch.save(vgg, tmp_path / "vgg.pth")
    torch.save(lin, tmp_path / "lin.pth")
    loaded = LPIPS.load(tmp_path / "vgg.pth", tmp_path / "lin.pth")
    a, b = image_pair(1)
    np.testing.assert_allclose(loaded(a, b).double().numpy(), REFERENCE, rtol=1e-5, atol=1e-9)
    del vgg["features.28.bias"]
    with pytest.raises(InvalidInputError, match=r"features\.28\.bias"):
        LPIPS(vgg, lin)
    with pytest.raises(InvalidInputError, match="lin4"):
        LPIPS(random_weights(0)[0], {k: v for k, v in lin.items() if "lin4" not in k})
    (tmp_path / "junk.pth").write_bytes(b"not a torch file")
    with pytest.raises(InvalidInputError, match=r"junk\.pth"):
        LPIPS.load(tmp_path / "junk.pth", tmp_path / "lin.pth")


def test_find_weights(tmp_path, monkeypatch):
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    monkeypatch.delenv("EDMCGS_LPIPS_VGG", raising=False)
    monkeypatch.delenv("EDMCGS_LPIPS_LIN", raising=False)
    monkeypatch.setattr("importlib.util.find_spec", lambda name: None)  # no lpips package installed
    assert find_weights() is None
    hub = tmp_path / "torch" / "hub" / "checkpoints"
    hub.mkdir(parents=True)
    (hub / "vgg16-397923af.pth").write_bytes(b"x")
    assert find_weights() is None  # the lin weights are still missing
    (tmp_path / "lin.pth").write_bytes(b"x")
    monkeypatch.setenv("EDMCGS_LPIPS_LIN", str(tmp_path / "lin.pth"))
    assert find_weights() == (hub / "vgg16-397923af.pth", tmp_path / "lin.pth")
    with pytest.raises(InvalidInputError, match="no such file"):
        find_weights(vgg=tmp_path / "missing.pth")


def test_missing_weights_names_each_file_and_where_it_goes(tmp_path, monkeypatch):
    import importlib.machinery

    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    monkeypatch.delenv("EDMCGS_LPIPS_VGG", raising=False)
    monkeypatch.delenv("EDMCGS_LPIPS_LIN", raising=False)
    monkeypatch.setattr("importlib.util.find_spec", lambda name: None)
    hub = tmp_path / "torch" / "hub" / "checkpoints" / "vgg16-397923af.pth"
    line = missing_weights()
    assert len(line.splitlines()) == 1
    assert f"vgg16-397923af.pth: not at {hub}" in line and "--lpips-vgg" in line
    assert "weights/v0.1/vgg.pth: the lpips package is not installed" in line
    # An installed lpips package: its own linear weights are the ones used, found beside its code.
    package = tmp_path / "site" / "lpips"
    (package / "weights" / "v0.1").mkdir(parents=True)
    (package / "__init__.py").write_text("")
    spec = importlib.machinery.ModuleSpec("lpips", None, origin=str(package / "__init__.py"))
    monkeypatch.setattr("importlib.util.find_spec", lambda name: spec if name == "lpips" else None)
    assert f"not at {package / 'weights' / 'v0.1' / 'vgg.pth'}" in missing_weights()
    (package / "weights" / "v0.1" / "vgg.pth").write_bytes(b"x")
    hub.parent.mkdir(parents=True)
    hub.write_bytes(b"x")
    assert missing_weights() == ""
    assert find_weights() == (hub, package / "weights" / "v0.1" / "vgg.pth")


def test_evaluation_scores_lpips_when_given_weights(metric, tmp_path, capsys):
    from edmcgs.cli import main
    from edmcgs.model.checkpoint import load_checkpoint
    from edmcgs.model.eval.evaluation import evaluate, summarize
    from edmcgs.pipeline import training_data
    from edmcgs.sensor.files.recording import read_recording
    from edmcgs.server import demo

    ckpt, rec = demo.files()
    data = training_data(read_recording(rec))
    rows = evaluate(load_checkpoint(ckpt), data, np.array([0, 20]), lpips=metric)
    assert all(r.lpips is not None and np.isfinite(r.lpips) and r.lpips > 0 for r in rows)
    assert summarize(rows)["lpips"] == pytest.approx(np.mean([r.lpips for r in rows]))
    assert main(["eval", "--demo", "--lpips-vgg", str(tmp_path / "missing.pth")]) == 1
    assert "missing.pth" in capsys.readouterr().err
