"""The thesis's performance test done properly: pose evaluation of crowds, keyframe against every other condition.

Stages: ``pose`` = every joint of every character sampled at the character's own random phase, plus forward
kinematics to model space; ``skin`` = the same plus linear blend skinning of the MakeHuman body; ``blend`` = the
run-time blending and additive jobs beside keyframe playback (:mod:`anim_core.bench.blend`).  Every clip of
the clip set given is timed (the thesis's keyframe and hybrid, and any other condition, e.g. those of
``server/clipset/conditions16.toml``), each against the keyframe clip of its animation in the same rounds.
Variants:

* ``keys``: the runtime that evaluates every clip from what it stores (:mod:`anim_core.runtime`): dense keys
  for a keyframe clip, fitted SQUAD segments for a gait or idle hybrid (half of them for a mirrored gait), the
  closed-form spring and unclamped slerp for the crouch; a ``reduced`` clip's keys at their own times, a
  ``quantized`` clip's integers dequantized in the kernel, a ``hybrid_c2`` clip's control points, a
  ``hybrid_ik`` clip's hybrid runtime plus its foot tracks and two-bone IK.  The headline figures.
  An ``update_rate`` clip is posed by the held-update path (:class:`anim_core.runtime.HeldCrowd`: a character
  only when its held pose changes).
* ``baked``: every hybrid baked into a uniform table of keys (:func:`anim_core.runtime.crowd.bake`), posed like a
  keyframe clip: the speed of dense keys bought with their memory.
* ``reference``: the numpy reference implementation (``clip.sample`` + ``Skeleton.forward_kinematics``), with
  SQUAD tangents precomputed when the clip is built.
* ``naive``: like ``reference``, but a SQUAD hybrid recomputes its tangents every frame, as an engine script
  that evaluates the spline from its keys would (the crouch's spring has no tangents and has no naive variant).

With ``keys``, four LOD variants of it (bone LOD 1 and 2: :data:`anim_core.runtime.BONE_LODS`; update-rate LOD:
each character re-posed every 2nd or 4th frame, staggered) and ``keys-fk-only`` (no joint sampled, every joint at
rest: what per-character set-up plus forward kinematics cost, for the per-stage profile) are timed at the large
crowds, and ``keys`` once more on all cores.

Cases of one animation are timed interleaved (A B A B ...) so that drift of a shared machine hits them alike.
"""

from __future__ import annotations

import os
import platform
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..clips import metrics
from ..clips.record import BuiltClip
from ..math.clip import KeyframeClip
from ..methods.c2spline import C2Clip
from ..methods.footlock import FootLockedClip
from ..methods.hybrid import SpringClip, SquadClip
from ..methods.lod import HeldClip
from ..runtime import (
    AnyRuntime,
    HeldRuntime,
    TableRuntime,
    angle_error_deg,
    animated_joints,
    bone_lod_mask,
    exact_global,
    lod_pose,
    pose_threads,
    runtime_for,
    sample_times,
)
from ..runtime.crowd import CrowdBuffers, bake, numba

DEFAULT_CHARACTERS = (1, 2, 5, 10, 20, 50, 100, 200, 1000, 10000)
VARIANTS = ("keys", "baked", "reference", "naive")
REFERENCE_MAX_CHARACTERS = 200  # numpy reference and naive variants: enough to compare, and bigger crowds take minutes
SKIN_MAX_CHARACTERS = 5  # skinning 13,380 vertices (~7 ms a character) costs the same for every method
SKIN_FRAMES = 50  # skinning dominates that stage; fewer frames keep the whole run short
NUMPY_FRAMES = 50  # the numpy variants take milliseconds a frame: their median is steady after fewer frames
LOD_FRAMES = 50  # the LOD and profile variants, timed at the large crowds only
SHORT_WARMUP = 5  # for rounds whose kernels are compiled already (or are numpy)
PARALLEL_MIN_CHARACTERS = 100
LOD_MIN_CHARACTERS = 1000  # LOD and profile variants: where a crowd's cost matters
BONE_LOD_LEVELS = (1, 2)
UPDATE_EVERY = (2, 4)
FPS = 60.0  # the characters' clocks advance by 1/60 s per benchmark frame
ACCURACY_OVERSAMPLING = 8  # accuracy: one period sampled at 8x the clip's frame rate (the issue asks >= 4x)


@dataclass(frozen=True)
class Case:
    """One thing to time: a clip in one variant."""

    animation: str
    condition: str
    method: str
    increment: int | None  # the hybrid's parameter, kept in the results for the thesis's figures
    variant: str
    step: Callable[[np.ndarray, int], Any]  # poses all characters at the given times, in the given frame


def lod_variants() -> list[tuple[str, dict[str, Any]]]:
    """Names of the keys runtime's LOD variants with what they change: ``bone_lod`` level or ``update_every``."""
    return ([(f"keys-bone-lod{lv}", {"bone_lod": lv}) for lv in BONE_LOD_LEVELS]
            + [(f"keys-every{k}", {"update_every": k}) for k in UPDATE_EVERY])


def _reference_step(clip: Any) -> Callable[[np.ndarray, int], Any]:
    sample = (lambda t: clip.sample(t, method="nlerp")) if isinstance(clip, KeyframeClip) else clip.sample
    return lambda t, _f: clip.skeleton.forward_kinematics(*sample(t))


def _naive_step(clip: SquadClip) -> Callable[[np.ndarray, int], Any]:
    """SQUAD from the keys every frame: tangents recomputed, then evaluated (what the thesis's Unity script did)."""
    return lambda t, _f: clip.skeleton.forward_kinematics(*clip.sample(t, controls=clip.tangents()))


def _runtime_step(runtime: AnyRuntime | HeldRuntime, n: int, parallel: bool = False, bone_lod: int = 0,
                  update_every: int = 1, fk_only: bool = False, clip: Any = None) -> Callable[[np.ndarray, int], Any]:
    """Pose ``n`` characters with ``runtime`` as the crowd plays its clip: a held clip by the held-update path, a
    bone-LOD ``clip`` (``bone_lod`` method) sampling only its animated joints (:func:`animated_joints`: the
    frozen ones are copied from their bind-pose key), and the LOD variants' joints held as they say."""
    if isinstance(runtime, HeldRuntime) and bone_lod == 0 and update_every == 1 and not fk_only:
        crowd = runtime.crowd(n)  # the held-update path: a character posed only when its held pose changes
        return lambda t, _f: crowd.pose(t, parallel)
    buffers = CrowdBuffers.for_crowd(n, runtime.skeleton.n_joints)
    active = bone_lod_mask(runtime.skeleton, bone_lod) if clip is None else animated_joints(clip, bone_lod)
    if fk_only:
        active = np.zeros_like(active)
    if update_every > 1:  # character c is re-posed in the frames where (frame + c) is a multiple of k
        return lambda t, f: runtime.pose(t, buffers, parallel, active, (-f) % update_every, update_every)
    return lambda t, _f: runtime.pose(t, buffers, parallel, active)


def _skinned(step: Callable[[np.ndarray, int], Any], mesh: Any) -> Callable[[np.ndarray, int], Any]:
    def run(t: np.ndarray, f: int) -> Any:
        out = step(t, f)
        return mesh.skin(mesh.skinning_matrices(out.rotations, out.positions))
    return run


def machine() -> dict[str, Any]:
    cpu = platform.processor() or ""
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next((line.split(":", 1)[1].strip() for line in f if line.startswith("model name")), cpu)
    except OSError:
        pass
    try:
        load = list(os.getloadavg())
    except OSError:
        load = None
    return {"cpu": cpu, "cores": os.cpu_count(), "python": platform.python_version(), "numpy": np.__version__,
            "numba": numba.__version__ if numba else None, "platform": platform.platform(), "load_average": load}


def interleaved_ms(steps: Sequence[Callable[[np.ndarray, int], Any]], phases: np.ndarray, frames: int, warmup: int,
                   seed: int = 0) -> list[list[float]]:
    """Per step, the milliseconds of each timed frame (``step(t, frame)``, ``t = phases + frame / FPS``), the steps
    timed interleaved in a new (seeded) order every frame: a shared machine's load hits them alike, and no step
    always follows the same one.  (In a fixed order, or one rotated, which keeps each step's predecessor, a step
    after one that posed the whole crowd finds the caches emptied: the update-rate ladder's pps4, timed after a
    joint-LOD clip, came out dearer than pps6 though it poses three quarters as many characters a frame.)"""
    times: list[list[float]] = [[] for _ in steps]
    order = np.random.default_rng(seed)
    for frame in range(warmup + frames):
        t = phases + frame / FPS
        for k in order.permutation(len(steps)):
            start = time.perf_counter()
            steps[k](t, frame)
            if frame >= warmup:
                times[k].append((time.perf_counter() - start) * 1000.0)
    return times


def _time(cases: Sequence[Case], phases: np.ndarray, frames: int, warmup: int) -> dict[int, list[float]]:
    """Per case (by index), the milliseconds of each timed frame (:func:`interleaved_ms`)."""
    return dict(enumerate(interleaved_ms([c.step for c in cases], phases, frames, warmup)))


def _case(c: BuiltClip, variant: str, step: Callable[[np.ndarray, int], Any]) -> Case:
    return Case(c.animation, c.condition, c.method, c.params.get("increment"), variant, step)


def reference_bytes(clip: Any, naive: bool = False) -> int:
    """Bytes of the arrays the numpy reference holds for a clip (float64): its keys, plus for a SQUAD clip the
    precomputed control points (not for ``naive``, which recomputes them) and the root spline's coefficients; a
    C2 clip's control points and knots beside its SQUAD clip's; a foot-locked clip's targets and weights and
    their splines beside its hybrid's; a quantized clip's dequantized keys (what it samples)."""
    if isinstance(clip, HeldClip):  # the reference's keys, sampled at held times
        return reference_bytes(clip.base)
    if isinstance(clip, SquadClip):
        seg_times, q, a, b, root = clip.precomputed()
        arrays = [clip.key_times, clip.key_rotations, clip.key_root, clip.velocity, seg_times, root.x, root.c]
        if not naive:
            arrays += [q, a, b]
    elif isinstance(clip, C2Clip):
        return reference_bytes(clip.squad) + int(clip.spline.control.nbytes + clip.spline.knots.nbytes)
    elif isinstance(clip, FootLockedClip):
        tracks = [a for spline in clip.tracks() for a in (spline.x, spline.c)]
        return reference_bytes(clip.base) + int(sum(a.nbytes for a in [clip.targets, clip.weights, *tracks]))
    elif isinstance(clip, SpringClip):
        arrays = [clip.key_params, clip.key_rotations, clip.key_root]
    else:  # keyframe
        arrays = [clip.times, clip.rotations, clip.root_translation, clip.velocity]
    return int(sum(np.asarray(a).nbytes for a in arrays))


def _accuracy(c: BuiltClip, variant: str, runtime: AnyRuntime | HeldRuntime | None, rate: float, lod: dict[str, Any]
              ) -> dict[str, float]:
    """Largest and mean angle (degrees) between a joint's global rotation from ``variant`` and from the exact
    curve; for a LOD variant also against the keys runtime without LOD (what the LOD alone costs)."""
    t = sample_times(c.clip, rate)
    exact, _ = exact_global(c.clip, t)
    if runtime is None:  # the numpy variants
        got, _ = (_naive_step(c.clip) if variant == "naive" else _reference_step(c.clip))(t, 0)
    else:
        got = lod_pose(runtime, t, **lod, frame_s=1.0 / FPS)
    worst, mean = angle_error_deg(got, exact)
    out = {"max_error_deg": worst, "mean_error_deg": mean}
    if lod:
        out["lod_max_error_deg"], out["lod_mean_error_deg"] = angle_error_deg(got, lod_pose(runtime, t))
    return out


def _runtimes(clips: Sequence[BuiltClip], variants: Sequence[str]) -> dict[str, dict[str, AnyRuntime | HeldRuntime]]:
    """Per timed variant (``keys``, ``baked``), each clip's runtime: a baked one keeps a keyframe or held clip's
    own (it is a table already)."""
    runtimes: dict[str, dict[str, AnyRuntime | HeldRuntime]] = {"keys": {}, "baked": {}}
    for c in clips:
        if "keys" in variants:
            runtimes["keys"][c.id] = runtime_for(c.clip)
        if "baked" in variants:
            runtimes["baked"][c.id] = (runtime_for(c.clip) if c.method == "keyframe" or isinstance(c.clip, HeldClip)
                                       else TableRuntime.from_table(bake(c.clip)))
    return runtimes


def _memory_and_accuracy(clips: Sequence[BuiltClip], runtimes: dict[str, dict[str, AnyRuntime | HeldRuntime]],
                         variants: Sequence[str]) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """The memory rows and accuracy rows of every clip x timed variant (the LOD variants ride on ``keys``)."""
    timed_variants = list(variants) + ([name for name, _ in lod_variants()] if "keys" in variants else [])
    memory: list[dict[str, Any]] = []
    accuracy: list[dict[str, Any]] = []
    lods = dict(lod_variants())
    for c in clips:
        label = {"clip": c.id, "animation": c.animation, "condition": c.condition, "method": c.method,
                 "increment": c.params.get("increment")}
        stored = c.metrics.get("bytes") or metrics.storage_bytes(c.key_times.size, c.character.skeleton.n_joints)
        rate = ACCURACY_OVERSAMPLING * c.fps
        for v in timed_variants:
            if v == "naive" and not isinstance(c.clip, SquadClip):
                continue
            base = "keys" if v in lods else v
            runtime = runtimes[base][c.id] if base in runtimes else None
            size = runtime.runtime_bytes if runtime is not None else reference_bytes(c.clip, naive=v == "naive")
            memory.append({**label, "variant": v, "stored_bytes": stored, "runtime_bytes": size})
            accuracy.append({**label, "variant": v, **_accuracy(c, v, runtime, rate, lods.get(v, {}))})
    return memory, accuracy


def _rounds(stage: str, group: Sequence[BuiltClip], n: int, runtimes: dict[str, dict[str, AnyRuntime | HeldRuntime]],
            variants: Sequence[str], frames: int, warmup: int) -> list[tuple[int, list[Case], int, int]]:
    """The timing rounds of one animation's clips at ``n`` characters: (threads, cases, frames, warm-up) each;
    the cases of a round are timed interleaved, so their ratios come from the same moments."""
    rounds: list[tuple[int, list[Case], int, int]] = []
    full = (frames, warmup) if stage == "pose" else (min(frames, SKIN_FRAMES), min(warmup, SHORT_WARMUP))
    short = (min(frames, NUMPY_FRAMES), min(warmup, SHORT_WARMUP))
    keyed = runtimes["keys"]
    for v in ("keys", "baked"):
        if v in variants and (stage == "pose" or v == "keys"):
            rounds.append((1, [_case(c, v, _runtime_step(runtimes[v][c.id], n, clip=c.clip)) for c in group], *full))
    if stage == "pose" and "keys" in variants:
        if n >= PARALLEL_MIN_CHARACTERS:
            rounds.append((pose_threads(), [_case(c, "keys", _runtime_step(keyed[c.id], n, parallel=True,
                                                                                 clip=c.clip))
                                                 for c in group], *full))
        if n >= LOD_MIN_CHARACTERS:
            lod_cases = [_case(c, "keys-fk-only", _runtime_step(keyed[c.id], n, fk_only=True)) for c in group]
            lod_cases += [_case(c, name, _runtime_step(keyed[c.id], n, **lod, clip=c.clip))
                          for name, lod in lod_variants() for c in group]
            rounds.append((1, lod_cases, min(frames, LOD_FRAMES), min(warmup, SHORT_WARMUP)))
    if stage == "pose" and n <= REFERENCE_MAX_CHARACTERS:
        numpy_cases = [_case(c, "reference", _reference_step(c.clip)) for c in group] if "reference" in variants \
            else []
        if "naive" in variants:
            numpy_cases += [_case(c, "naive", _naive_step(c.clip)) for c in group if isinstance(c.clip, SquadClip)]
        if numpy_cases:
            rounds.append((1, numpy_cases, *short))
    return rounds


def _timed_rows(stage: str, rounds: list[tuple[int, list[Case], int, int]], mesh: Any, phases: np.ndarray,
                n: int) -> list[dict[str, Any]]:
    """Time ``rounds`` (skinned on ``mesh`` for the ``skin`` stage): one result row per case."""
    rows = []
    for threads, round_cases, n_frames, n_warmup in rounds:
        if stage == "skin":
            round_cases = [Case(k.animation, k.condition, k.method, k.increment, k.variant, _skinned(k.step, mesh))
                           for k in round_cases]
        timed = _time(round_cases, phases, n_frames, n_warmup)
        for i, case in enumerate(round_cases):
            ms = np.asarray(timed[i])
            median = float(np.median(ms))
            rows.append({"animation": case.animation, "condition": case.condition, "method": case.method,
                         "increment": case.increment, "variant": case.variant, "stage": stage,
                         "characters": n, "threads": threads, "median_ms": median,
                         "p95_ms": float(np.percentile(ms, 95)), "fps": 1000.0 / median, "frames": len(ms)})
    return rows


def run(clips: Sequence[BuiltClip], characters: Sequence[int] = DEFAULT_CHARACTERS,
        stages: Sequence[str] = ("pose", "skin"), frames: int = 200, warmup: int = 20, seed: int = 2017,
        variants: Sequence[str] = VARIANTS, progress: Callable[[str], None] = lambda _m: None) -> dict[str, Any]:
    """Time every animation x method x variant x stage x crowd size; returns the results document."""
    unknown = [v for v in variants if v not in VARIANTS]
    if unknown or not variants:
        raise ValueError(f"variants are {', '.join(VARIANTS)}, got {', '.join(variants) or 'none'}")
    rng = np.random.default_rng(seed)
    started = time.perf_counter()
    runtimes = _runtimes(clips, variants)
    progress(f"runtimes built ({time.perf_counter() - started:.0f} s)")
    memory, accuracy = _memory_and_accuracy(clips, runtimes, variants)
    progress(f"memory and accuracy measured ({time.perf_counter() - started:.0f} s)")

    results: list[dict[str, Any]] = []
    animations = list(dict.fromkeys(c.animation for c in clips))
    blend_memory: list[dict[str, Any]] = []
    for stage in stages:
        if stage == "blend":  # the blending jobs beside playback (issue 39): anim_core.bench.blend
            from .blend import blend_stage

            rows, blend_memory = blend_stage(clips, characters, frames, warmup, rng, _time)
            results += rows
            progress(f"  blend: done ({time.perf_counter() - started:.0f} s)")
            continue
        for n in [n for n in characters if stage == "pose" or n <= SKIN_MAX_CHARACTERS]:
            for animation in animations:
                group = [c for c in clips if c.animation == animation]
                phases = rng.uniform(0.0, 2 * max(float(c.clip.duration) for c in group), n)
                results += _timed_rows(stage, _rounds(stage, group, n, runtimes, variants, frames, warmup),
                                       group[0].character.mesh, phases, n)
            progress(f"  {stage}: {n} characters done ({time.perf_counter() - started:.0f} s)")
    return {"machine": machine(), "settings": {"frames": frames, "skin_frames": min(frames, SKIN_FRAMES),
                                               "numpy_frames": min(frames, NUMPY_FRAMES),
                                               "lod_frames": min(frames, LOD_FRAMES),
                                               "warmup": warmup, "seed": seed, "characters": list(characters),
                                               "stages": list(stages), "variants": list(variants),
                                               "clock_per_frame_s": 1 / FPS,
                                               "accuracy_samples_per_frame": ACCURACY_OVERSAMPLING},
            "results": results, "memory": memory, "accuracy": accuracy, "blend_memory": blend_memory,
            "summary": summarize(results, memory, accuracy)}


def _ratios(results: Sequence[dict[str, Any]], variant: str) -> list[dict[str, Any]]:
    """Every condition's median over its animation's keyframe clip's, from the same rounds (pose, one thread)."""
    base = [r for r in results if r["stage"] == "pose" and r["variant"] == variant and r["threads"] == 1]
    keyframe = {(r["animation"], r["characters"]): r["median_ms"] for r in base if r["method"] == "keyframe"}
    return [{"animation": r["animation"], "condition": r["condition"], "method": r["method"],
             "increment": r["increment"], "characters": r["characters"], "median_ms": r["median_ms"],
             "ratio": r["median_ms"] / keyframe[(r["animation"], r["characters"])]}
            for r in base if r["method"] != "keyframe" and (r["animation"], r["characters"]) in keyframe]


def summarize(results: Sequence[dict[str, Any]], memory: Sequence[dict[str, Any]] = (),
              accuracy: Sequence[dict[str, Any]] = ()) -> dict[str, Any]:
    """The goals' figures: hybrid / keyframe median ratios (stage pose, one thread; ``keys`` variant, and every
    other compiled variant), the largest crowd's worst time, the multi-core speed-up, memory and accuracy.
    ``ratios`` holds every condition's ratio (``method`` says which); the hybrid goals' figures are the
    hybrids'."""
    ratios = _ratios(results, "keys")
    at_10 = [x["ratio"] for x in ratios if x["characters"] >= 10 and x["method"] == "hybrid"]
    base = [r for r in results if r["stage"] == "pose" and r["variant"] == "keys"]
    biggest = max((r["characters"] for r in base), default=0)
    serial = {(r["animation"], r["method"], r["increment"]): r["median_ms"]
              for r in base if r["characters"] == biggest and r["threads"] == 1}
    speedups = [serial[(r["animation"], r["method"], r["increment"])] / r["median_ms"]
                for r in base if r["characters"] == biggest and r["threads"] > 1
                and (r["animation"], r["method"], r["increment"]) in serial]
    keyframe_bytes = {m["animation"]: m["runtime_bytes"] for m in memory
                      if m["variant"] == "keys" and m["method"] == "keyframe"}
    memory_ratios = [{"clip": m["clip"], "increment": m["increment"],
                      "ratio": m["runtime_bytes"] / keyframe_bytes[m["animation"]]}
                     for m in memory if m["variant"] == "keys" and m["method"] == "hybrid"
                     and m["animation"] in keyframe_bytes]
    hybrid_errors = [a["max_error_deg"] for a in accuracy if a["variant"] == "keys" and a["method"] == "hybrid"]
    other = {v: [x["ratio"] for x in _ratios(results, v) if x["characters"] >= 10 and x["method"] == "hybrid"]
             for v in ("baked",)}
    return {
        "ratios": ratios,
        "max_ratio_at_10_or_more": max(at_10) if at_10 else None,
        "median_ratio_at_10_or_more": float(np.median(at_10)) if at_10 else None,
        "max_ratio_at_10_or_more_by_variant": {v: max(x) if x else None for v, x in other.items()},
        "largest_crowd": biggest,
        "largest_crowd_worst_ms": max((r["median_ms"] for r in base if r["characters"] == biggest
                                       and r["threads"] == 1), default=None),
        "parallel_threads": max((r["threads"] for r in base), default=1),
        "parallel_speedup_min": min(speedups) if speedups else None,
        "parallel_speedup_median": float(np.median(speedups)) if speedups else None,
        "memory_ratios": memory_ratios,
        "max_memory_ratio_increment_0": max((m["ratio"] for m in memory_ratios if m["increment"] == 0),
                                            default=None),
        "max_hybrid_error_deg": max(hybrid_errors) if hybrid_errors else None,
    }


def series(results: Sequence[dict[str, Any]], stage: str = "pose") -> list[dict[str, Any]]:
    """Average over animations (and increments) of the median ms per frame, per method/variant, for plots; every
    other method of the results from its keys too."""
    out = []
    others = [m for m in dict.fromkeys(r["method"] for r in results) if m not in ("keyframe", "hybrid")]
    for name, keep in (
        ("keyframe", lambda r: r["method"] == "keyframe" and r["variant"] == "keys"),
        ("hybrid, from its keys", lambda r: r["method"] == "hybrid" and r["variant"] == "keys"),
        *((f"{m}, from its keys", lambda r, m=m: r["method"] == m and r["variant"] == "keys") for m in others),
        ("hybrid, baked table", lambda r: r["method"] == "hybrid" and r["variant"] == "baked"),
        ("keyframe, numpy reference", lambda r: r["method"] == "keyframe" and r["variant"] == "reference"),
        ("hybrid, numpy reference", lambda r: r["method"] == "hybrid" and r["variant"] == "reference"),
        ("hybrid, naive SQUAD", lambda r: r["method"] == "hybrid" and r["variant"] == "naive"),
    ):
        rows = [r for r in results if r["stage"] == stage and r["threads"] == 1 and keep(r)]
        ns = sorted({r["characters"] for r in rows})
        points = [[n, float(np.mean([r["median_ms"] for r in rows if r["characters"] == n]))] for n in ns]
        if points:
            out.append({"name": name, "points": points})
    return out


COLORS = ("#555555", "#2166ac", "#b2182b", "#4d9221", "#e08214", "#8073ac", "#67a9cf", "#c51b7d")


def svg_chart(lines: Sequence[dict[str, Any]], title: str, x_label: str, y_label: str) -> str:
    """A log-log line chart as SVG text: ``lines`` = [{"name", "points": [[x, y], ...], "dashed"?}]."""
    w, h, left, right, top, bottom = 760, 440, 70, 190, 40, 50
    xs = [p[0] for s in lines for p in s["points"]]
    ys = [p[1] for s in lines for p in s["points"] if p[1] > 0]
    x0, x1 = np.log10(min(xs)), np.log10(max(xs))
    y0, y1 = np.floor(np.log10(min(ys))), np.ceil(np.log10(max(ys)))
    x1, y1 = (x1 if x1 > x0 else x0 + 1), (y1 if y1 > y0 else y0 + 1)

    def px(v: float) -> float:
        return left + (np.log10(v) - x0) / (x1 - x0) * (w - left - right)

    def py(v: float) -> float:
        return h - bottom - (np.log10(v) - y0) / (y1 - y0) * (h - top - bottom)

    out = [f'<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 {w} {h}" font-family="sans-serif" '
           f'font-size="12"><rect width="{w}" height="{h}" fill="white"/>',
           f'<text x="{left}" y="22" font-size="15" font-weight="bold">{title}</text>']
    for e in range(int(y0), int(y1) + 1):
        y = py(10.0**e)
        out.append(f'<line x1="{left}" x2="{w - right}" y1="{y:.1f}" y2="{y:.1f}" stroke="#e3e7ee"/>'
                   f'<text x="{left - 6}" y="{y + 4:.1f}" text-anchor="end">{10.0**e:g}</text>')
    for x in sorted(set(xs)):
        out.append(f'<line x1="{px(x):.1f}" x2="{px(x):.1f}" y1="{top}" y2="{h - bottom}" stroke="#f0f2f5"/>'
                   f'<text x="{px(x):.1f}" y="{h - bottom + 16}" text-anchor="middle">{x:g}</text>')
    out.append(f'<text x="{(left + w - right) / 2}" y="{h - 12}" text-anchor="middle">{x_label}</text>'
               f'<text x="16" y="{(top + h - bottom) / 2}" transform="rotate(-90 16 {(top + h - bottom) / 2})" '
               f'text-anchor="middle">{y_label}</text>')
    for i, s in enumerate(lines):
        color = COLORS[i % len(COLORS)]
        d = " ".join(f"{'L' if k else 'M'}{px(x):.1f},{py(y):.1f}" for k, (x, y) in enumerate(s["points"]) if y > 0)
        dash = ' stroke-dasharray="6 4"' if s.get("dashed") else ""
        out.append(f'<path d="{d}" fill="none" stroke="{color}" stroke-width="2"{dash}/>')
        ly = top + 14 + 18 * i
        out.append(f'<line x1="{w - right + 12}" x2="{w - right + 36}" y1="{ly - 4}" y2="{ly - 4}" stroke="{color}" '
                   f'stroke-width="2"{dash}/><text x="{w - right + 42}" y="{ly}">{s["name"]}</text>')
    out.append("</svg>")
    return "\n".join(out)


def _fps_lines(results: Sequence[dict[str, Any]], groups: Sequence[tuple[str, Callable[[dict], bool], bool]]
               ) -> list[dict[str, Any]]:
    lines = []
    for name, keep, dashed in groups:
        rows = [r for r in results if r["stage"] == "pose" and r["threads"] == 1 and keep(r)]
        ns = sorted({r["characters"] for r in rows})
        pts = [[n, float(np.mean([r["fps"] for r in rows if r["characters"] == n]))] for n in ns]
        if pts:
            lines.append({"name": name, "points": pts, "dashed": dashed})
    return lines


def svg_bars(groups: Sequence[str], bars: Sequence[dict[str, Any]], title: str, y_label: str) -> str:
    """Grouped bars on a log y axis as SVG text: one group per label, ``bars`` = [{"name", "values": [...]}]
    with one value (or None) per group."""
    w, h, left, right, top, bottom = 1000, 460, 70, 150, 40, 110
    ys = [v for b in bars for v in b["values"] if v]
    y0, y1 = np.floor(np.log10(min(ys) / 3)), np.ceil(np.log10(max(ys)))  # the smallest bar stays visible
    y1 = y1 if y1 > y0 else y0 + 1
    group_w = (w - left - right) / max(1, len(groups))
    bar_w = max(2.0, (group_w - 6) / max(1, len(bars)))

    def py(v: float) -> float:
        return h - bottom - (np.log10(v) - y0) / (y1 - y0) * (h - top - bottom)

    out = [f'<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 {w} {h}" font-family="sans-serif" '
           f'font-size="12"><rect width="{w}" height="{h}" fill="white"/>',
           f'<text x="{left}" y="22" font-size="15" font-weight="bold">{title}</text>',
           f'<text x="16" y="{(top + h - bottom) / 2}" transform="rotate(-90 16 {(top + h - bottom) / 2})" '
           f'text-anchor="middle">{y_label}</text>']
    for e in range(int(y0), int(y1) + 1):
        y = py(10.0**e)
        out.append(f'<line x1="{left}" x2="{w - right}" y1="{y:.1f}" y2="{y:.1f}" stroke="#e3e7ee"/>'
                   f'<text x="{left - 6}" y="{y + 4:.1f}" text-anchor="end">{10.0**e:g}</text>')
    for g, label in enumerate(groups):
        x0 = left + g * group_w + 3
        for k, b in enumerate(bars):
            v = b["values"][g]
            if v:
                out.append(f'<rect x="{x0 + k * bar_w:.1f}" y="{py(v):.1f}" width="{bar_w - 1:.1f}" '
                           f'height="{h - bottom - py(v):.1f}" fill="{COLORS[k % len(COLORS)]}">'
                           f'<title>{label} {b["name"]}: {v:g}</title></rect>')
        cx = x0 + group_w / 2
        out.append(f'<text x="{cx:.1f}" y="{h - bottom + 12}" text-anchor="end" '
                   f'transform="rotate(-45 {cx:.1f} {h - bottom + 12})">{label}</text>')
    for k, b in enumerate(bars):
        ly = top + 14 + 18 * k
        out.append(f'<rect x="{w - right + 12}" y="{ly - 10}" width="14" height="12" '
                   f'fill="{COLORS[k % len(COLORS)]}"/><text x="{w - right + 32}" y="{ly}">{b["name"]}</text>')
    out.append("</svg>")
    return "\n".join(out)


def memory_bars(memory: Sequence[dict[str, Any]]) -> tuple[list[str], list[dict[str, Any]]]:
    """Runtime bytes per clip (groups) and variant (bars), for :func:`svg_bars` and the dashboard."""
    clips = list(dict.fromkeys(m["clip"] for m in memory))
    variants = [v for v in VARIANTS if any(m["variant"] == v for m in memory)]
    by = {(m["clip"], m["variant"]): m["runtime_bytes"] for m in memory}
    bars = [{"name": "stored keys", "values": [next(m["stored_bytes"] for m in memory if m["clip"] == c)
                                               for c in clips]}]
    bars += [{"name": v, "values": [by.get((c, v)) for c in clips]} for v in variants]
    return clips, bars


def write_plots(doc: dict[str, Any], out_dir: Any) -> list[Any]:
    """The thesis's figures 4.5 (average keyframe against average hybrid), 4.6 (per increment) and 4.7 (per
    animation) from the ``keys`` variant, as FPS against characters on log axes, and the runtime bytes per clip
    and variant; returns the files written."""
    from pathlib import Path

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    r = doc["results"]
    keys = lambda m: (lambda x: x["method"] == m and x["variant"] == "keys")  # noqa: E731
    others = [m for m in dict.fromkeys(x["method"] for x in r) if m not in ("keyframe", "hybrid")]
    figures = {
        "fps_average.svg": ("Average keyframe against average hybrid (pose, one thread)", _fps_lines(r, [
            ("keyframe", keys("keyframe"), False), ("hybrid (from its keys)", keys("hybrid"), False),
            *((f"{m} (from its keys)", keys(m), False) for m in others),
            ("hybrid, baked table", lambda x: x["method"] == "hybrid" and x["variant"] == "baked", True),
            ("keyframe, numpy reference", lambda x: x["method"] == "keyframe" and x["variant"] == "reference", True),
            ("hybrid, numpy reference", lambda x: x["method"] == "hybrid" and x["variant"] == "reference", True),
            ("hybrid, naive SQUAD", lambda x: x["method"] == "hybrid" and x["variant"] == "naive", True)])),
        "fps_increment.svg": ("Per increment (pose, one thread, from the keys)", _fps_lines(r, [
            ("keyframe", keys("keyframe"), False)] + [
            (f"hybrid increment {i}", lambda x, i=i: keys("hybrid")(x) and x["increment"] == i, False)
            for i in sorted({x["increment"] for x in r if x["method"] == "hybrid"})])),
        "fps_animation.svg": ("Per animation (pose, one thread, from the keys)", _fps_lines(r, [
            (f"{a} {m}", lambda x, a=a, m=m: keys(m)(x) and x["animation"] == a, m == "keyframe")
            for a in dict.fromkeys(x["animation"] for x in r) for m in ("keyframe", "hybrid")])),
    }
    written = []
    for name, (title, lines) in figures.items():
        if lines:
            path = out / name
            path.write_text(svg_chart(lines, title, "characters", "frames per second"), encoding="utf-8")
            written.append(path)
    if doc.get("memory"):
        groups, bars = memory_bars(doc["memory"])
        path = out / "runtime_bytes.svg"
        path.write_text(svg_bars(groups, bars, "Runtime bytes per clip and variant", "bytes"), encoding="utf-8")
        written.append(path)
    return written
