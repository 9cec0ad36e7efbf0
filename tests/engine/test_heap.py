"""The C heap under a host memory bound (``engine.heap``): freed arrays leave the resident set."""

from __future__ import annotations

import subprocess
import sys

import pytest

from engine import heap

SCENARIO = """
import sys
import numpy as np
from engine import heap

def rss():
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) << 10 for line in f if line.startswith("VmRSS"))

if sys.argv[1] == "bound":
    assert heap.bound_heap()
a = np.ones(30 << 20, np.uint8)  # mapped, and when freed glibc raises its threshold to 30 MiB
del a
base = rss()
blocks = [np.ones(2 << 20, np.uint8) for _ in range(40)]  # 80 MiB: from the heap once the threshold was raised
top = np.ones(1 << 16, np.uint8)  # above them, so the heap's top is not free
del blocks
held = rss() - base
heap.give_back()
print(held >> 20, (rss() - base) >> 20)
"""


def _held_mib(mode: str) -> tuple[int, int]:
    done = subprocess.run([sys.executable, "-c", SCENARIO, mode], capture_output=True, text=True, check=True)
    held, after = done.stdout.split()
    return int(held), int(after)


@pytest.mark.skipif(heap._glibc() is None, reason="engine.heap acts on glibc only")
def test_freed_arrays_leave_the_resident_set_under_a_bound() -> None:
    """80 MiB of 2 MiB arrays freed below a live one: glibc's heap keeps them resident (its threshold raised by an
    earlier big block) until they are given back; with the bound's fixed threshold they were never in the heap."""
    held, after = _held_mib("plain")
    assert held >= 60 and after <= 8, (held, after)
    held, after = _held_mib("bound")
    assert held <= 8 and after <= 8, (held, after)


def test_nothing_is_done_where_the_c_library_is_not_glibc(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(heap, "_glibc", lambda: None)
    assert heap.bound_heap() is False
    heap.give_back()  # no error
