"""Whether a RUNNING run is still alive (its process, its heartbeat tags), and marking the dead ones
KILLED: a run killed outright (SIGKILL, a lost machine) never ends itself."""

from __future__ import annotations

import os
import socket
import time
from pathlib import Path


def process_started(pid: int) -> str:
    """When process ``pid`` started, "" if it cannot be told: with the pid it tells the run's
    process from a later one that was given the same pid."""
    import psutil  # lazy: psutil (~0.1 s), kept off `fedlgr --help`

    try:
        return f"{psutil.Process(pid).create_time():.2f}"
    except (psutil.Error, OSError):
        return ""


def process_alive(pid: int, started: str = "") -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    try:  # a killed child its parent has not reaped yet is a zombie: dead
        if Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0] == "Z":
            return False
    except OSError:
        return True
    return not started or process_started(pid) in ("", started)  # not the pid of a later process


def dead_reason(run, now: float | None = None) -> str | None:
    """Why a RUNNING run is dead (its process is gone, or its heartbeat stopped), or None while it
    may be alive. The heartbeat only judges runs on other machines (a process here may be stopped by
    Ctrl-Z); runs without one (sweep parents) are never dead."""
    tags = run.data.tags
    if run.info.status != "RUNNING" or "fedlgr.heartbeat" not in tags:
        return None
    pid = tags.get("fedlgr.pid", "")
    here = tags.get("fedlgr.host") == socket.gethostname()
    if here and pid.isdigit():
        if process_alive(int(pid), tags.get("fedlgr.pid_started", "")):
            return None
        return f"its process {pid} on this machine is gone"
    age = (now or time.time()) - float(tags["fedlgr.heartbeat"])
    limit = 3 * float(tags.get("fedlgr.heartbeat_s", 30))
    if age > limit:
        return f"no heartbeat for {age:.0f} s (limit {limit:.0f} s)"
    return None


def end_dead_runs(client, experiment_ids: list[str]) -> list[str]:
    """Mark the dead RUNNING runs of these experiments KILLED; their ids."""
    runs = client.search_runs(experiment_ids, "attributes.status = 'RUNNING'", max_results=5000)
    ended = []
    for run in runs:
        reason = dead_reason(run)
        if reason is not None:
            client.set_tag(run.info.run_id, "fedlgr.ended", f"marked KILLED: {reason}")
            client.set_terminated(run.info.run_id, "KILLED")
            ended.append(run.info.run_id)
    return ended
