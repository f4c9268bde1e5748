"""The allocator tuning the CLI and the executor workers apply (msmem_core.util.malloc)."""

from __future__ import annotations

import json
import platform
import subprocess
import sys

import pytest

PROBE = """
import json, resource, sys
import numpy as np
from msmem_core.util.malloc import keep_large_allocations

def faults():  # minor page faults of one 64 MB temporary, every page written
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    a = np.ones(16 * 1024 * 1024, dtype=np.float32)
    del a
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before

untuned = [faults(), faults()]
ok = keep_large_allocations()
tuned = [faults(), faults()]
print(json.dumps({"ok": ok, "untuned": untuned, "tuned": tuned}))
"""


def test_large_temporaries_are_reused_instead_of_page_faulted_again():
    if platform.libc_ver()[0] != "glibc":
        pytest.skip("not glibc: keep_large_allocations is a no-op there")
    r = json.loads(subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, check=True).stdout)
    assert r["ok"]
    assert r["untuned"][1] > 0, r  # untuned, each 64 MB temporary is a fresh mmap, faulted page by page
    assert r["tuned"][1] < r["untuned"][1] // 10, r  # tuned, the freed block is reused
