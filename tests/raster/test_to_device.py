"""``render.io.to_device``: host values onto a device, on a GPU without waiting for its queue."""

import numpy as np
import pytest
import torch

from edmcgs.model.render.io import to_device


def test_on_the_cpu_the_values_arrive_as_they_are():
    host = np.array([[1.0, 2.0], [3.0, 4.0]], dtype=np.float32)
    out = to_device(host, "cpu")
    assert out.device.type == "cpu" and out.dtype == torch.float32
    assert torch.equal(out, torch.from_numpy(host))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_on_cuda_the_copy_does_not_synchronise():
    busy = torch.rand(4096, 4096, device="cuda")
    host = torch.arange(16, dtype=torch.float32).reshape(4, 4)
    to_device(host, "cuda")  # the first pinned block is allocated (cudaHostAlloc may wait); later reuse it
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")  # any synchronising call raises
    try:
        for _ in range(5):
            busy = busy @ busy / 4096  # the queue is busy when the copy is issued
            out = to_device(host, "cuda")
    finally:
        torch.cuda.set_sync_debug_mode("default")
    assert out.device.type == "cuda"
    assert torch.equal(out.cpu(), host)  # the copy ran in stream order, from a buffer kept alive
