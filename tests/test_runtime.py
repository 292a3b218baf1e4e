"""Thread settings per device."""

from ogmapping.runtime import torch_threads_for


def test_cpu_mapping_uses_one_torch_thread_and_cuda_several():
    assert torch_threads_for("cpu") == 1
    assert 1 <= torch_threads_for("cuda") <= 8
