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


def run_ccx(folder: Path, job: str = "knee_ccx", timeout_s: float = 1800.0) -> Run:
    """Run ``ccx -i job`` in ``folder`` on :data:`CCX_THREADS` threads under a time limit.

    Raises ``ccx_missing`` when ccx is not installed and ``deck_skipped`` when ccx skipped part
    of the deck; a run that stops early (no convergence, time limit) is returned with its reason.
    """
    exe = shutil.which("ccx")
    if exe is None:
        raise KneeMeshError("ccx_missing", INSTALL_HINT)
    t0 = time.perf_counter()
    env = {**os.environ, "OMP_NUM_THREADS": str(CCX_THREADS)}
    try:
        p = subprocess.run([exe, "-i", job], cwd=folder, capture_output=True, text=True, timeout=timeout_s, env=env)
        log, rc = p.stdout + p.stderr, p.returncode
    except subprocess.TimeoutExpired as exc:
        log = (exc.stdout or b"").decode(errors="replace") if isinstance(exc.stdout, bytes) else (exc.stdout or "")
        (folder / f"{job}.log").write_text(log)
        return Run(False, f"stopped at the time limit of {timeout_s:g} s", time.perf_counter() - t0, log, ccx_version(exe))
    (folder / f"{job}.log").write_text(log)
    skipped = [line.strip() for line in log.splitlines() if SKIPPED.search(line)]
    if skipped:
        raise KneeMeshError("deck_skipped", f"ccx skipped part of the deck ({len(skipped)} lines, e.g. {skipped[0]!r}); "
                            f"the run proves nothing: see {folder / (job + '.log')}.")
    errors = [line.strip() for line in log.splitlines() if "*ERROR" in line]
    seconds = time.perf_counter() - t0
    if rc != 0 or errors or "Job finished" not in log:
        why = errors[0] if errors else f"ccx exited {rc}"
        return Run(False, why, seconds, log, ccx_version(exe))
    return Run(True, None, seconds, log, ccx_version(exe))
