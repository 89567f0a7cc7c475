"""`senfunet replay` as a command, for the tests that check what it prints and writes."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path


def replay_commands(*jobs: tuple[Path | str, Path, Path], compare: bool = False,
                    timeout_s: float = 600) -> list[subprocess.CompletedProcess]:
    """`senfunet replay BAG --out OUT --params PARAMS --no-progress [--compare]` for each
    (BAG, OUT, PARAMS), all at once (each process spends most of its seconds loading libraries)."""
    procs = []
    for bag, out, params in jobs:
        argv = [sys.executable, "-m", "senfunet_ros.cli", "replay", str(bag), "--out", str(out), "--params",
                str(params), "--no-progress", *(["--compare"] if compare else [])]
        procs.append((argv, subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)))
    done = []
    for argv, proc in procs:
        stdout, stderr = proc.communicate(timeout=timeout_s)
        done.append(subprocess.CompletedProcess(argv, proc.returncode, stdout, stderr))
    return done
