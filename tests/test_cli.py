"""The command line as a shell user meets it."""

from __future__ import annotations

import os
import subprocess
import sys


def test_a_closed_pipe_ends_quietly(data):
    """`animstudy inspect | head -1`: the reader closes the pipe early; no traceback, exit status 1."""
    env = {**os.environ, "ANIMSTUDY_DATA_DIR": str(data)}
    proc = subprocess.Popen([sys.executable, "-m", "server.cli", "inspect"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, env=env)
    assert proc.stdout is not None and proc.stderr is not None
    assert proc.stdout.readline().startswith(b"motion capture in")
    proc.stdout.close()
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=60) == 1
    assert "Traceback" not in err and "BrokenPipeError" not in err, err
