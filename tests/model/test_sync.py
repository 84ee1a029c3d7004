"""GradientSync in a group of one (gloo, in this process): what it exchanges and what it counts."""

import pytest
import torch
import torch.distributed as dist

from edmcgs.model.motion.row_grad import at_rows
from edmcgs.model.train.row_adam import RowAdam
from edmcgs.model.train.sync import GradientSync


@pytest.fixture
def group(tmp_path):
    dist.init_process_group("gloo", init_method=f"file://{tmp_path / 'rendezvous'}", rank=0, world_size=1)
    try:
        yield
    finally:
        dist.destroy_process_group()


def test_a_step_s_exchange_is_counted_in_bytes_and_seconds(group):
    sync = GradientSync()
    assert (sync.rank, sync.world, sync.seconds, sync.bytes) == (0, 1, 0.0, 0)
    means = torch.nn.Parameter(torch.randn(10, 3))
    net = torch.nn.Parameter(torch.randn(4))
    opt = RowAdam([{"name": "means", "params": [means]}, {"name": "deform", "params": [net]}],
                  row_groups=("means",), lr=0.1)
    means.grad, net.grad = torch.ones(10, 3), torch.full((4,), 2.0)
    rows = sync.union(torch.tensor([7, 2, 2]))
    assert rows.tolist() == [2, 7]
    after_union = sync.bytes
    assert after_union == 8 + 3 * 8  # the row count, then the padded rows (int64)
    sync.average(opt, opt.row_groups, rows)
    # the drawn rows of the per-Gaussian group, the whole of the others, and one flag per parameter
    assert sync.bytes - after_union == (2 * 3 + 4 + 2) * 4
    # the per-Gaussian group's gradient comes back at its rows alone (sparse, as a window's comes)
    assert means.grad.is_sparse and torch.equal(at_rows(means.grad, rows), torch.ones(2, 3))
    assert torch.equal(net.grad, torch.full((4,), 2.0))
    sync.sum_(torch.zeros(5))
    assert sync.bytes - after_union == (2 * 3 + 4 + 2 + 5) * 4
    assert sync.seconds > 0.0
