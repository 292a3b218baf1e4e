"""The mapper's torch thread setting: one thread for sparse maps on the CPU, only for its own calls."""

import threading

import torch

from ogmapping.runtime.profile import execution_profile
from ogmapping.runtime.threads import torch_threads


def test_sparse_cpu_maps_use_one_thread_others_keep_the_callers():
    assert execution_profile("cpu", "auto", "anchor").threads == 1
    assert execution_profile("cpu", "auto", "hash").threads is None
    assert execution_profile("cuda", "torch", "anchor").threads is None


def test_setting_is_restored_and_stays_on_the_calling_thread():
    before = torch.get_num_threads()
    seen: dict[str, int] = {}
    inside = threading.Event()
    release = threading.Event()

    def worker() -> None:
        with torch_threads(1):
            seen["worker"] = torch.get_num_threads()
            inside.set()
            release.wait(10)

    thread = threading.Thread(target=worker)
    thread.start()
    inside.wait(10)
    seen["main"] = torch.get_num_threads()
    release.set()
    thread.join()
    assert seen == {"worker": 1, "main": before}
    with torch_threads(None):
        assert torch.get_num_threads() == before
    with torch_threads(1):
        assert torch.get_num_threads() == 1
    assert torch.get_num_threads() == before
