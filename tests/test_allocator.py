"""glibc keeps freed image-sized blocks after ``import ogmapping``, so reusing them costs no page faults."""

import platform
import resource

import numpy as np
import pytest

import ogmapping  # noqa: F401  (the import applies the setting)
from ogmapping.runtime.allocator import keep_freed_memory

pytestmark = pytest.mark.skipif(platform.system() != "Linux" or platform.libc_ver()[0] != "glibc",
                                reason="mallopt thresholds are glibc's")


def _minor_faults() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt


def test_setting_applies():
    assert keep_freed_memory()


def _render_like_step() -> float:
    """Three image-sized buffers alive at once, then all freed: one mapping step's pattern."""
    buffers = [np.ones(2**20, np.float32) for _ in range(3)]  # 4 MB each
    return sum(float(b.sum()) for b in buffers)


def test_freed_image_buffers_are_reused_without_faulting_pages_in_again():
    _render_like_step()  # the heap grows once
    before = _minor_faults()
    for _ in range(20):
        _render_like_step()
    # glibc's defaults return the freed 12 MB to the system every step: ~20k faults here.
    assert _minor_faults() - before < 1024
