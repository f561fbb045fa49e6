"""Ctrl-C for the tests: a job started as a terminal would, interrupted once it is busy; and a
deadline that turns a hang into a failure."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import time
from collections.abc import Callable
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": str(ROOT / "src")}


def start_job(command: list[str]) -> subprocess.Popen:
    """The job in a process group of its own, with Ctrl-C's default handling even when the tests
    run in the background (a shell starts background jobs with SIGINT ignored, and an ignored
    signal stays ignored through exec). ``command[0]`` must be Python: a first interpreter
    restores SIGINT's default, then becomes the job by exec (no Python code runs between fork
    and exec, which is unsafe in a process with threads such as this one)."""
    restore = "import os, signal, sys; signal.signal(signal.SIGINT, signal.SIG_DFL); "
    restore += "os.execv(sys.argv[1], sys.argv[1:])"
    return subprocess.Popen(
        [command[0], "-c", restore, *command],
        env=ENV,
        start_new_session=True,
        text=True,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )


def interrupt_when(
    job: subprocess.Popen, ready: Callable[[], bool], seconds: float = 600
) -> tuple[str, str]:
    """SIGINT to the job's process group (as Ctrl-C in a terminal) once ``ready()``; returns
    the job's (stdout, stderr). A job that ends first or is not ready in time fails the test."""
    deadline = time.monotonic() + seconds
    try:
        while not ready():
            assert job.poll() is None, job.communicate()
            assert time.monotonic() < deadline, f"not ready after {seconds} s"
            time.sleep(0.05)
        os.killpg(job.pid, signal.SIGINT)
        return job.communicate(timeout=120)
    finally:
        if job.poll() is None:
            os.killpg(job.pid, signal.SIGKILL)  # leave no job behind a failed test


@contextlib.contextmanager
def deadline(seconds: float, what: str):
    """Raise TimeoutError in the main thread after ``seconds`` (a hang becomes a failure)."""

    def expire(*_):
        raise TimeoutError(f"{what} hung for {seconds} s")

    previous = signal.signal(signal.SIGALRM, expire)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)
