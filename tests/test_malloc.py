"""The allocator tuning the CLI and the executor workers apply (msmem_core._malloc)."""

from __future__ import annotations

import platform
import resource

import numpy as np
import pytest

from msmem_core._malloc import keep_large_allocations


def _faults_of_a_64mb_temporary() -> int:
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    a = np.ones(16 * 1024 * 1024, dtype=np.float32)  # 64 MB, every page written
    del a
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before


def test_large_temporaries_are_reused_instead_of_page_faulted_again():
    if platform.libc_ver()[0] != "glibc":
        pytest.skip("not glibc: keep_large_allocations is a no-op there")
    assert keep_large_allocations()
    first = _faults_of_a_64mb_temporary()  # grows the heap (untuned: a fresh mmap, faulted every time)
    again = _faults_of_a_64mb_temporary()
    assert first > 0 and again < first // 10, (first, again)
