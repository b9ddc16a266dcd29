"""The allocator options of the node processes: a freed sweep-sized block stays mapped and is reused."""
import subprocess
import sys
import textwrap

import pytest

# In a thread other than the main one (where the nodes run), allocate a 100 MB array, touch every
# page, free it, and allocate it again; print the resident memory (MB) the freed block left mapped and
# how much the second allocation added.
PROBE = textwrap.dedent("""
    import os, threading
    import numpy as np
    from gls_calibration.ros.allocator import keep_freed_memory
    applied = keep_freed_memory()
    page_mb = os.sysconf("SC_PAGE_SIZE") / 2**20
    resident_mb = lambda: int(open("/proc/self/statm").read().split()[1]) * page_mb
    out = []

    def run():
        before = resident_mb()
        block = np.ones(100 * 2**20 // 8)
        del block
        kept = resident_mb() - before
        block = np.ones(100 * 2**20 // 8)
        out.extend([kept, resident_mb() - before - kept])
    worker = threading.Thread(target=run)
    worker.start()
    worker.join()
    print(applied, *out)
""")


def probe(environment_switch: str) -> tuple[str, float, float]:
    import os

    env = {**os.environ, "GLS_KEEP_FREED_MEMORY": environment_switch}
    done = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, timeout=120, env=env)
    assert done.returncode == 0, done.stderr[-2000:]
    applied, kept_mb, added_mb = done.stdout.split()
    return applied, float(kept_mb), float(added_mb)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's allocator")
def test_a_freed_sweep_sized_block_stays_mapped_and_is_reused():
    applied, kept_mb, added_mb = probe("1")
    assert applied == "True"
    assert kept_mb > 90.0           # freed, its pages stay with the process ...
    assert added_mb < 10.0          # ... and the next block of that size takes them: no new pages to zero


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's allocator")
def test_switched_off_glibc_maps_each_block_anew():
    # the same probe with glibc's defaults: what the options avoid (shows the check above can fail)
    applied, kept_mb, added_mb = probe("0")
    assert applied == "False"
    assert kept_mb < 10.0 and added_mb > 90.0
