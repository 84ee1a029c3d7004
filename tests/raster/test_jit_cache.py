"""numba's on-disk cache: ``jit.compiled`` tells whether a kernel is in it, the commands announce a compile
that is still to come, and ``edmcgs warm-up`` fills the cache with what they compile."""

import importlib.util
import logging
import types

import numba
import numpy as np
import torch

from edmcgs.model.render import rasterize, rasterize_fast
from edmcgs.model.render.jit import compiled


def _module(path, name):
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_compiled_tells_a_kernel_in_the_cache_from_one_still_to_compile(tmp_path):
    source = tmp_path / "kernels_under_test.py"
    source.write_text("from edmcgs.model.render.jit import njit_cached\n\n"
                      "@njit_cached()\ndef twice(x):\n    return 2 * x\n")
    first = _module(source, "kernels_under_test")
    assert not compiled(first.twice)
    assert first.twice(np.arange(3.0)).tolist() == [0.0, 2.0, 4.0]
    assert compiled(first.twice)
    assert compiled(_module(source, "kernels_under_test").twice)  # another import: the cache is found
    source.write_text(source.read_text() + "\n# an edit\n")  # a changed source: its cache is stale
    assert not compiled(_module(source, "kernels_under_test").twice)
    assert not compiled(numba.njit(cache=False)(lambda x: x))  # no cache at all: always compiled anew


def test_serve_and_train_announce_a_compile_only_when_one_is_coming(monkeypatch, caplog, capsys):
    from edmcgs import train_cli
    from edmcgs.server import service

    engine = types.SimpleNamespace(model=types.SimpleNamespace(center=torch.zeros(1, 3)), warm_up=lambda: 1.5)
    for cached in (True, False):
        monkeypatch.setattr(service, "compiled", lambda *kernels, c=cached: c)
        monkeypatch.setattr("edmcgs.model.render.jit.compiled", lambda *kernels, c=cached: c)
        with caplog.at_level(logging.INFO, logger="edmcgs.server"):
            caplog.clear()
            assert service._warm_up(engine) == 1.5
        train_cli._announce_compile()
        said = [r.getMessage() for r in caplog.records], capsys.readouterr().out
        if cached:
            assert said == ([], "")
        else:
            assert f"about {rasterize_fast.COMPILE_S} s" in said[0][0] and "first run only" in said[0][0]
            assert f"about {rasterize.COMPILE_S + rasterize_fast.COMPILE_S} s" in said[1]


def test_warm_up_leaves_every_kernel_the_commands_compile_in_the_cache(capsys):
    from edmcgs.cli import main
    from edmcgs.synth import esim

    assert main(["warm-up"]) == 0
    assert "numba kernels in the cache" in capsys.readouterr().out
    assert compiled(*rasterize_fast.KERNELS, *rasterize.KERNELS, esim._log_serial, esim._emit_serial)
