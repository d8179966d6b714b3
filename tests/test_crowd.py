"""The crowd fast path against the reference implementation, and a short benchmark run."""

import json
import xml.etree.ElementTree as ET
from itertools import pairwise

import numpy as np
import pytest

from anim_core.bench import suite as benchmark
from anim_core.math import quat as Q
from anim_core.math.clip import KeyframeClip
from anim_core.runtime import pose_crowd
from anim_core.runtime.crowd import BAKE_TOLERANCE_DEG, bake, numba, pose_crowd_numpy, table_from_keyframes
from tests.synthetic import biped, random_rotations


@pytest.fixture(scope="module")
def clips(built_clip_set):
    return built_clip_set()


def reference(clip, t):
    pose = clip.sample(t, method="nlerp") if isinstance(clip, KeyframeClip) else clip.sample(t)
    return clip.skeleton.forward_kinematics(*pose)


def test_numba_is_present():
    assert numba is not None  # otherwise the fallback would be what the benchmark measures


def test_fast_path_matches_the_reference_for_every_clip(clips, rng):
    t = rng.uniform(-5.0, 15.0, 400)  # negative, several periods, both ping-pong directions
    for c in clips:
        table = table_from_keyframes(c.clip) if c.method == "keyframe" else bake(c.clip)
        ref_rot, ref_pos = reference(c.clip, t)
        fast = pose_crowd(table, t)
        angle = np.degrees(Q.quat_angle(fast.rotations.astype(np.float64), ref_rot)).max()
        distance = np.linalg.norm(fast.positions - ref_pos, axis=-1).max()
        # Keyframe tables are the clip's own keys: only float32 rounding.  Baked hybrids: the stated tolerance.
        limit = 1e-3 if c.method == "keyframe" else BAKE_TOLERANCE_DEG
        assert angle <= limit, f"{c.id}: {angle:.4f} degrees"
        assert distance <= (1e-4 if c.method == "keyframe" else 0.01), f"{c.id}: {distance * 1000:.2f} mm"
        # The compiled kernel and the numpy evaluation of the same table agree; threads change nothing.
        rot_np, pos_np = pose_crowd_numpy(table, t)
        assert np.degrees(Q.quat_angle(fast.rotations.astype(np.float64), rot_np)).max() < 1e-3
        assert np.abs(fast.positions - pos_np).max() < 1e-4
        parallel = pose_crowd(table, t, parallel=True)
        assert np.array_equal(parallel.rotations, fast.rotations)
        assert np.array_equal(parallel.positions, fast.positions)


def test_travelling_loops_keep_walking(rng):
    skeleton = biped()
    times = np.arange(31) / 30.0
    rot = Q.make_continuous(random_rotations(rng, (31, skeleton.n_joints)), axis=0)
    root = np.cumsum(rng.normal(scale=0.01, size=(31, 3)), axis=0)
    root[:, 2] += np.linspace(0.0, 1.2, 31)
    for in_place in (False, True):
        clip = KeyframeClip(skeleton, times, rot, root, mode="loop", in_place=in_place)
        t = rng.uniform(0.0, 5.0, 200)
        ref_rot, ref_pos = reference(clip, t)
        fast = pose_crowd(table_from_keyframes(clip), t)
        assert np.abs(fast.positions - ref_pos).max() < 1e-5
        assert np.degrees(Q.quat_angle(fast.rotations.astype(np.float64), ref_rot)).max() < 1e-3


def test_short_benchmark_run_writes_results_and_plots(clips, tmp_path):
    few = [c for c in clips if c.animation in ("walk", "crouch")]
    doc = benchmark.run(few, characters=(1, 10), stages=("pose", "skin"), frames=3, warmup=1)  # skin: only 1
    keys = {"animation", "condition", "method", "increment", "variant", "stage", "characters", "threads",
            "median_ms", "p95_ms", "fps"}
    assert all(keys <= set(r) for r in doc["results"])
    variants = {(r["variant"], r["method"]) for r in doc["results"]}
    assert {("keys", "keyframe"), ("keys", "hybrid"), ("baked", "hybrid"), ("reference", "keyframe"),
            ("naive", "hybrid")} <= variants
    assert not any(r["variant"] == "naive" and r["animation"] == "crouch" for r in doc["results"])  # no tangents
    assert {r["stage"] for r in doc["results"]} == {"pose", "skin"}
    assert {r["variant"] for r in doc["results"] if r["stage"] == "skin"} == {"keys"}
    assert all(r["median_ms"] > 0 and r["fps"] == pytest.approx(1000 / r["median_ms"]) for r in doc["results"])
    assert {"cpu", "numpy", "cores"} <= set(doc["machine"])

    lods = [name for name, _ in benchmark.lod_variants()]
    memory = {(m["clip"], m["variant"]): m for m in doc["memory"]}
    for c in few:
        expected = {"keys", "baked", "reference", *lods} | ({"naive"} if c.animation == "walk" and c.method == "hybrid"
                                                             else set())
        assert {v for clip, v in memory if clip == c.id} == expected
    assert all(m["runtime_bytes"] > 0 and m["stored_bytes"] > 0 for m in doc["memory"])
    assert {"clip", "animation", "condition", "method", "increment", "variant", "stored_bytes",
            "runtime_bytes"} == set(doc["memory"][0])
    assert {(r["animation"], r["condition"]) for r in doc["results"]} == {(c.animation, c.condition) for c in few}
    # Keyframe clips: keys and baked are the same table; a hybrid's keys runtime is far smaller than its table.
    assert memory[("walk-keyframe", "keys")]["runtime_bytes"] == memory[("walk-keyframe", "baked")]["runtime_bytes"]
    for c in few:
        if c.method == "hybrid":
            assert memory[(c.id, "keys")]["runtime_bytes"] < memory[(c.id, "baked")]["runtime_bytes"]
    errors = {(a["clip"], a["variant"]): a["max_error_deg"] for a in doc["accuracy"]}
    assert set(errors) == set(memory)
    assert all(errors[(c.id, "keys")] <= 0.25 for c in few)
    assert all(errors[(c.id, "reference")] < 1e-5 for c in few)  # the reference is the exact curve (rounding)
    assert errors[("walk-hybrid0", "keys-every4")] > errors[("walk-hybrid0", "keys-every2")] > 0

    s = doc["summary"]
    assert s["largest_crowd"] == 10 and s["max_ratio_at_10_or_more"] > 0
    assert 0 < s["max_memory_ratio_increment_0"] < 1 and s["max_hybrid_error_deg"] <= 0.25
    json.dumps(doc)  # serialisable as it is
    written = benchmark.write_plots(doc, tmp_path)
    assert {p.name for p in written} == {"fps_average.svg", "fps_increment.svg", "fps_animation.svg",
                                         "runtime_bytes.svg"}
    for p in written:
        root = ET.fromstring(p.read_text())
        assert len(root.findall("{http://www.w3.org/2000/svg}path")) + len(
            root.findall("{http://www.w3.org/2000/svg}rect")) >= 3


def test_benchmark_lod_and_parallel_rounds_at_large_crowds(clips, monkeypatch):
    monkeypatch.setattr(benchmark, "LOD_MIN_CHARACTERS", 20)
    monkeypatch.setattr(benchmark, "PARALLEL_MIN_CHARACTERS", 20)
    idle = [c for c in clips if c.animation == "idle"]
    doc = benchmark.run(idle, characters=(20,), stages=("pose",), frames=2, warmup=1, variants=("keys",))
    timed = {(r["variant"], r["threads"]) for r in doc["results"]}
    assert {("keys", 1), ("keys-fk-only", 1), ("keys-bone-lod1", 1), ("keys-every4", 1)} <= timed
    assert any(v == "keys" and n > 1 for v, n in timed) and doc["summary"]["parallel_speedup_min"] > 0
    assert {m["variant"] for m in doc["memory"]} == {"keys", *[n for n, _ in benchmark.lod_variants()]}
    with pytest.raises(ValueError, match="variants are"):
        benchmark.run(idle, characters=(1,), variants=("fast",))


def test_bench_steps_are_timed_in_a_new_order_every_frame():
    """No step always follows the same one (a step after a full-crowd pose finds the caches emptied: in a fixed
    or rotated order the update-rate ladder's pps4 came out dearer than pps6); every step timed every frame."""
    from anim_core.bench.suite import interleaved_ms

    calls: list[int] = []
    steps = [lambda _t, _f, k=k: calls.append(k) for k in range(5)]
    timed = interleaved_ms(steps, np.zeros(3), frames=40, warmup=2)
    assert [len(ms) for ms in timed] == [40] * 5
    assert len(calls) == 42 * 5
    predecessors: dict[int, set[int]] = {k: set() for k in range(5)}
    for before, after in pairwise(calls):
        predecessors[after].add(before)
    assert all(len(p) >= 3 for p in predecessors.values())
