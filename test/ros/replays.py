"""`senfunet replay` as a command, for the tests that check what it prints and writes."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path


def _args(bag: Path | str, out: Path, params: Path, compare: bool) -> list[str]:
    return ["replay", str(bag), "--out", str(out), "--params", str(params), "--no-progress",
            *(["--compare"] if compare else [])]


def replay_commands(*jobs: tuple[Path | str, Path, Path], compare: bool = False,
                    timeout_s: float = 600) -> list[subprocess.CompletedProcess]:
    """`senfunet replay BAG --out OUT --params PARAMS --no-progress [--compare]` for each
    (BAG, OUT, PARAMS), all at once (each process spends most of its seconds loading libraries)."""
    procs = []
    for bag, out, params in jobs:
        argv = [sys.executable, "-m", "senfunet_ros.cli", *_args(bag, out, params, compare)]
        procs.append((argv, subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)))
    done = []
    for argv, proc in procs:
        stdout, stderr = proc.communicate(timeout=timeout_s)
        done.append(subprocess.CompletedProcess(argv, proc.returncode, stdout, stderr))
    return done


def replay_in_process(bag: Path | str, out: Path, params: Path, *, compare: bool = False
                      ) -> subprocess.CompletedProcess:
    """The same command's `cli.main` in this process (no library loading), its output captured and
    the signal handlers it sets restored afterwards."""
    import contextlib
    import io
    import signal

    from senfunet_ros import cli

    argv = _args(bag, out, params, compare)
    stdout, stderr = io.StringIO(), io.StringIO()
    handlers = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
            code = cli.main(argv)
    finally:
        for sig, handler in handlers.items():
            signal.signal(sig, handler)
    return subprocess.CompletedProcess(argv, code, stdout.getvalue(), stderr.getvalue())
