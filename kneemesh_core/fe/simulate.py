"""Run CalculiX on a job's ``fe/knee_ccx.inp`` and refuse a run that does not prove the deck.

ccx skips an unknown keyword or parameter with a warning and still exits 0; a run is accepted
only when ccx exits 0, says ``Job finished``, prints no ``*ERROR`` and no line saying it skipped
part of the deck (``../shared/docs/fe-calculix-reference.md``, section 4).
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

from kneemesh_core.errors import KneeMeshError

#: Lines that mean ccx ignored part of the deck although it may exit 0.
SKIPPED = re.compile(r"cannot be interpreted|not recognized|not applicable|card image", re.IGNORECASE)
INSTALL_HINT = ("CalculiX (ccx) is not installed: `apt-get install calculix-ccx` (Debian/Ubuntu, as root), "
                "or `make test`, which installs it where it can.")


@dataclass
class Run:
    completed: bool
    reason: str | None
    seconds: float
    log: str
    version: str | None


def ccx_version(exe: str) -> str | None:
    try:
        out = subprocess.run([exe, "-v"], capture_output=True, text=True, timeout=30).stdout
    except (OSError, subprocess.TimeoutExpired):
        return None
    m = re.search(r"Version\s+([0-9.]+)", out)
    return f"ccx {m.group(1)}" if m else None


#: ccx threads: two where there are two cores (the sample's smoke run: 64 s on one thread, 51 s on
#: two, the same 21 Newton iterations, on the 2-core machine).
CCX_THREADS = max(1, min(2, os.cpu_count() or 1))


#: A run that has used this much CPU time (s, all its threads) since its last converged increment has
#: stalled and is stopped: when a contact's active set cycles between two states, ccx cuts the increment
#: back and retries for ever (OAI 9357383_00m: its patella's tip touching the trochlea's edge, 115 contact
#: elements on and off at every iteration, 25 min on the smoke run between 6.6 and 6.7 deg).  Converging
#: increments take 10-60 s of one thread.  CPU time, not wall time: a run that shares the cores with
#: others waits without progress and is not stalled (a wall-clock limit stopped a healthy run at 0 deg
#: while four processes shared the two cores).
STALL_CPU_S = 600.0
#: The same for a model with deformable cartilage, whose Newton iterations cost 15-25 CPU seconds on the
#: sample (rigid: 1-3): its first attempt at a 5 deg flexion increment failed after 8 iterations and the
#: second after 5, 600 s in all, and the run was stopped before ccx's next cutback could converge.
DEFORMABLE_STALL_CPU_S = 3000.0
#: How often the .sta file is read while ccx runs, s.
POLL_S = 1.0


def cpu_seconds(pid: int) -> float | None:
    """CPU time (s, user and system, every thread, and its children that have ended) a running process has
    used, from ``/proc``; None where there is no ``/proc`` (the stall check then falls back to wall time)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return sum(int(x) for x in fields[11:15]) / os.sysconf("SC_CLK_TCK")


def last_converged(sta: Path) -> float | None:
    """The total time of the last converged increment in a ccx ``.sta`` file (None before the first):
    its rows are step, increment, attempt (with a ``U`` when the attempt did not converge),
    iterations, total time, step time, increment time."""
    try:
        lines = sta.read_text().splitlines()
    except OSError:
        return None
    for line in reversed(lines):
        parts = line.split()
        if len(parts) == 7 and parts[0].isdigit() and parts[2].isdigit():
            return float(parts[4])
    return None


def _watch(p: subprocess.Popen, sta: Path, t0: float, timeout_s: float, stall_s: float) -> str | None:
    """Wait for ccx, reading its ``.sta`` every :data:`POLL_S`; kill it at the time limit or once it has
    used ``stall_s`` CPU seconds (wall seconds where ``/proc`` is missing) since its last converged
    increment, and say why; None when it ended by itself."""
    progress, since = None, None
    while True:
        try:
            p.wait(timeout=POLL_S)
            return None
        except subprocess.TimeoutExpired:
            pass
        now = time.perf_counter()
        cpu, converged = cpu_seconds(p.pid), last_converged(sta)
        clock = now if cpu is None else cpu
        if since is None or converged != progress:
            progress, since = converged, clock
        stopped = None
        if now - t0 > timeout_s:
            stopped = f"stopped at the time limit of {timeout_s:g} s"
        elif clock - since > stall_s:
            stopped = (f"stalled: no increment converged in {stall_s:g} s of {'wall' if cpu is None else 'CPU'} time after "
                       f"step time {progress or 0:g} (ccx cutting the increment back again and again, as when a contact "
                       "keeps switching on and off)")
        if stopped:
            p.kill()
            p.wait()
            return stopped


def run_ccx(folder: Path, job: str = "knee_ccx", timeout_s: float = 1800.0, stall_s: float = STALL_CPU_S) -> Run:
    """Run ``ccx -i job`` in ``folder`` on :data:`CCX_THREADS` threads under a time limit (wall, s), stopping
    it when it has used ``stall_s`` seconds of CPU (:data:`STALL_CPU_S`) since its last converged increment.

    Raises ``ccx_missing`` when ccx is not installed and ``deck_skipped`` when ccx skipped part
    of the deck; a run that stops early (no convergence, stalled, time limit) is returned with its reason.
    """
    exe = shutil.which("ccx")
    if exe is None:
        raise KneeMeshError("ccx_missing", INSTALL_HINT)
    t0 = time.perf_counter()
    env = {**os.environ, "OMP_NUM_THREADS": str(CCX_THREADS)}
    log_path, sta = folder / f"{job}.log", folder / f"{job}.sta"
    sta.unlink(missing_ok=True)  # a .sta of an earlier run would read as progress
    with log_path.open("w") as log_file:
        p = subprocess.Popen([exe, "-i", job], cwd=folder, stdout=log_file, stderr=subprocess.STDOUT, env=env)
        stopped = _watch(p, sta, t0, timeout_s, stall_s)
    rc, log = p.returncode, log_path.read_text(errors="replace")
    if stopped:
        return Run(False, stopped, time.perf_counter() - t0, log, ccx_version(exe))
    skipped = [line.strip() for line in log.splitlines() if SKIPPED.search(line)]
    if skipped:
        raise KneeMeshError("deck_skipped", f"ccx skipped part of the deck ({len(skipped)} lines, e.g. {skipped[0]!r}); "
                            f"the run proves nothing: see {log_path}.")
    errors = [line.strip() for line in log.splitlines() if "*ERROR" in line]
    seconds = time.perf_counter() - t0
    if rc != 0 or errors or "Job finished" not in log:
        why = errors[0] if errors else f"ccx exited {rc}"
        return Run(False, why, seconds, log, ccx_version(exe))
    return Run(True, None, seconds, log, ccx_version(exe))
