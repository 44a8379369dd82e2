"""The command line's worker processes never outlive it."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # A zombie (ended, not yet reaped by its new parent) counts as ended.
    try:
        return Path(f"/proc/{pid}/stat").read_text().split()[2] != "Z"
    except OSError:
        return False


def test_workers_end_when_the_command_is_killed(tmp_path):
    # The parent is killed with SIGKILL (no handler runs): its workers find it gone and end.
    code = textwrap.dedent(
        """
        import os, sys, time
        from o3dreg.cli._common import process_pool
        with process_pool(2) as pool:
            pids = {f.result() for f in [pool.submit(os.getpid) for _ in range(8)]}
            busy = [pool.submit(time.sleep, 60) for _ in range(2)]
            print(" ".join(map(str, sorted(pids))), flush=True)
            time.sleep(60)
        """
    )
    proc = subprocess.Popen(
        [sys.executable, "-c", code], stdout=subprocess.PIPE, text=True,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )  # fmt: skip
    assert proc.stdout is not None
    workers = [int(p) for p in proc.stdout.readline().split()]
    assert workers and all(_alive(p) for p in workers)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=10)
    # The workers check for their parent every PARENT_CHECK_SECONDS (0.5 s): 10 s is ample.
    deadline = time.monotonic() + 10.0
    while any(_alive(p) for p in workers) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not any(_alive(p) for p in workers)
