"""`nhfd bench load`'s idle figures come from /proc: the CPU time it reads is the kernel's own
account of the process (as `times()` gives it), and a process that is gone reads as None."""

from __future__ import annotations

import os
import subprocess
import sys

from nhfd.benchmarks.load import cpu_percent, cpu_s


def test_cpu_time_is_the_kernels_account_and_a_gone_process_is_none():
    sum(i * i for i in range(300_000))  # some CPU time of our own to read
    t = os.times()
    ours = cpu_s(os.getpid())
    assert ours is not None and abs(ours - (t.user + t.system)) <= 0.02  # a clock tick or two
    child = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                           capture_output=True, text=True, check=True)
    gone = int(child.stdout)
    assert cpu_s(gone) is None
    assert cpu_percent({"gone": gone, "none": None}, 0.01) == {"gone": None, "none": None}
