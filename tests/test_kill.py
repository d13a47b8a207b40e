"""A run killed by a signal leaves no worker processes behind."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest


def _children(pid: int) -> list[int]:
    """The processes whose parent is ``pid`` (from /proc)."""
    out = []
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            stat = (d / "stat").read_text()
        except OSError:
            continue
        # pid (comm) state ppid ...: comm may hold spaces, so split after its ')'
        if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
            out.append(int(d.name))
    return out


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def _cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_text()
    except OSError:
        return ""


_SCRIPT = """
import time
from pylensfit.runner import run_tasks, worker_pool

def task(t):
    time.sleep(120)
    return t["i"]

if __name__ == "__main__":
    tasks = [{"i": i} for i in range(4)]
    if SHARED:  # the pool that several passes share (measure, the precision mode)
        with worker_pool(2) as pool:
            for _ in run_tasks(task, tasks, 2, None, "t", False, pool=pool):
                pass
    else:  # one call's own pool
        for _ in run_tasks(task, tasks, 2, None, "t", False):
            pass
"""


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="needs /proc")
@pytest.mark.parametrize("shared", [False, True])
def test_pool_workers_end_with_a_killed_run(tmp_path, shared):
    """SIGKILL to a process running tasks on the runner's pool: its workers, busy with
    long tasks, end within a few seconds instead of running on as orphans."""
    script = tmp_path / "run.py"
    script.write_text(_SCRIPT.replace("SHARED", str(shared)))
    proc = subprocess.Popen([sys.executable, str(script)], cwd=tmp_path)
    try:
        workers: list[int] = []
        deadline = time.monotonic() + 90
        while time.monotonic() < deadline and len(workers) < 2:
            time.sleep(0.5)
            workers = [p for p in _children(proc.pid) if _alive(p)]
            # the spawn start method runs a resource tracker beside the workers
            workers = [p for p in workers if "resource_tracker" not in _cmdline(p)]
        assert len(workers) >= 2, "the pool's workers did not start"
        time.sleep(2.0)  # the workers are in their tasks
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=10)
        deadline = time.monotonic() + 15
        while time.monotonic() < deadline and any(_alive(p) for p in workers):
            time.sleep(0.5)
        left = [p for p in workers if _alive(p)]
        for p in left:
            os.kill(p, signal.SIGKILL)
        assert not left, f"workers {left} outlived the killed run"
    finally:
        if proc.poll() is None:
            proc.kill()
