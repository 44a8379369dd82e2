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


def test_workers_busy_at_an_interrupt_are_ended_not_waited_for(tmp_path):
    # An exception in the block (Ctrl-C raises KeyboardInterrupt there) ends the running workers
    # at once: the command must not wait a minute for two 60 s tasks.
    code = textwrap.dedent(
        """
        import os, sys, time
        from o3dreg.cli._common import process_pool
        try:
            with process_pool(2) as pool:
                pids = {f.result() for f in [pool.submit(os.getpid) for _ in range(8)]}
                busy = [pool.submit(time.sleep, 60) for _ in range(2)]
                print(" ".join(map(str, sorted(pids))), flush=True)
                time.sleep(0.5)
                raise KeyboardInterrupt
        except KeyboardInterrupt:
            print("interrupted", flush=True)
        """
    )
    start = time.monotonic()
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=50,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )  # fmt: skip
    lines = out.stdout.split("\n")
    workers = [int(p) for p in lines[0].split()]
    assert lines[1] == "interrupted", out.stderr
    # Terminated workers end in well under the tasks' 60 s (the interpreter's start included).
    assert time.monotonic() - start < 30
    assert workers and not any(_alive(p) for p in workers)
