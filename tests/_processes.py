"""Run a test's Python snippet in several localhost processes (``jax.distributed`` checks) and collect the
``RESULT {json}`` line each prints; shared by tests/test_channels.py and tests/test_parallel_mblocks.py."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def free_port() -> int:
    """A free localhost TCP port for the coordinator."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def run_processes(code: str, args_per_process: list[list[str]], env: dict, timeout_s: float) -> list[dict]:
    """Start ``python -c code *args`` once per entry of ``args_per_process`` (all at once, in ROOT), wait for
    all within ``timeout_s`` in total, and return each one's last ``RESULT`` json; a non-zero exit or a
    timeout fails the test with the process's stderr, and every process left is killed."""
    procs, t0 = [], time.time()
    for args in args_per_process:
        procs.append(subprocess.Popen([sys.executable, "-c", code, *map(str, args)], env=env, cwd=ROOT,
                                      stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True))
    outs = []
    try:
        for p in procs:
            try:
                so, se = p.communicate(timeout=max(1.0, timeout_s - (time.time() - t0)))
            except subprocess.TimeoutExpired as exc:
                pytest.fail(f"a process did not finish in {timeout_s} s: {str(exc.stderr)[-4000:]}")
            assert p.returncode == 0, se[-6000:]
            outs.append(json.loads([ln for ln in so.splitlines() if ln.startswith("RESULT ")][-1][7:]))
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.communicate()
    return outs
