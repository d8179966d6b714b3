"""The command line as a shell user meets it."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest


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


@pytest.mark.slow  # tens of seconds (the serial run's slowest; still run by `make test`)
def test_bench_times_every_condition_of_a_clip_set(data, tmp_path):
    """`animstudy bench --quick --config conditions16.toml`: every clip of that clip set is timed from its keys,
    beside its animation's keyframe clip, and listed with its cost and ratio; a bad clip-set file is an error."""
    import json

    config = os.path.join(os.path.dirname(__file__), "..", "server", "clipset", "conditions16.toml")
    env = {**os.environ, "ANIMSTUDY_DATA_DIR": str(data), "ANIMSTUDY_VAR_DIR": str(tmp_path / "var")}
    out = tmp_path / "bench.json"
    run = subprocess.run([sys.executable, "-m", "server.cli", "bench", "--quick", "--config", config, "--characters",
                          "2", "--frames", "2", "--json", str(out)], capture_output=True, text=True, env=env,
                         timeout=900)
    assert run.returncode == 0, run.stderr
    doc = json.loads(out.read_text())
    assert doc["settings"]["variants"] == ["keys"] and doc["settings"]["stages"] == ["pose"]
    timed = {(r["animation"], r["condition"]) for r in doc["results"] if r["variant"] == "keys"}
    assert len(timed) == 56 and {m for _, m in timed} >= {"hybrid_ik0", "hybrid_c2_0", "reduced5", "quantized8"}
    assert len(doc["summary"]["ratios"]) == 52  # every clip but the 4 keyframe clips
    for animation, condition in timed:  # one line per clip: its ms and, but for the keyframe clip, its ratio
        line = next(x for x in run.stdout.splitlines() if x.startswith(f"{animation}-{condition} "))
        assert "(" in line and float(line.split()[1]) > 0, line
    bad = tmp_path / "bad.toml"
    bad.write_text("fps = 30\n", encoding="utf-8")
    run = subprocess.run([sys.executable, "-m", "server.cli", "bench", "--quick", "--config", str(bad)],
                         capture_output=True, text=True, env=env, timeout=300)
    assert run.returncode != 0 and "bad.toml" in run.stderr + run.stdout and "Traceback" not in run.stderr
