"""bench.report caches trained runs by the resolved config: a retuned preset trains again."""

from bench.report.training import run_key
from edmcgs.model.config import preset


def test_a_run_is_cached_under_its_resolved_config():
    demo = preset("demo")
    key = run_key("rec", demo.to_dict(), "cpu", False)
    assert key == run_key("rec", preset("demo").to_dict(), "cpu", False)
    assert key != run_key("rec", demo.replace(event_pool=demo.event_pool + 1).to_dict(), "cpu", False)
    assert key != run_key("rec", demo.replace(lambda_event=0.05).to_dict(), "cpu", False)
    assert key != run_key("other", demo.to_dict(), "cpu", False)
    reordered = dict(reversed(demo.to_dict().items()))  # the same values listed in another order
    assert run_key("rec", reordered, "cpu", False) == key
