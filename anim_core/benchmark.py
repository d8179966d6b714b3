"""The thesis's performance test done properly: pose evaluation of crowds, keyframe against hybrid.

Stages: ``pose`` = every joint of every character sampled at the character's own random phase, plus forward
kinematics to model space; ``skin`` = the same plus linear blend skinning of the MakeHuman body.  Variants:

* ``default``: the runtime path (:mod:`anim_core.crowd`): keyframe keys as they are, hybrids baked into tables.
* ``reference``: the numpy reference implementation (``clip.sample`` + ``Skeleton.forward_kinematics``), with
  SQUAD tangents precomputed when the clip is built.
* ``naive``: like ``reference``, but a SQUAD hybrid recomputes its tangents every frame, as an engine script
  that evaluates the spline from its keys would (the crouch's spring has no tangents and has no naive variant).

Keyframe and hybrid are timed interleaved (A B A B ...) so that drift of a shared machine hits both alike.
"""

from __future__ import annotations

import os
import platform
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from . import metrics
from .clipset import BuiltClip
from .crowd import CrowdBuffers, PoseTable, bake, numba, pose_crowd, table_from_keyframes
from .hybrid import SquadClip

DEFAULT_CHARACTERS = (1, 2, 5, 10, 20, 50, 100, 200, 1000, 10000)
REFERENCE_MAX_CHARACTERS = 200  # numpy reference and naive variants: enough to compare, and bigger crowds take minutes
SKIN_MAX_CHARACTERS = 5  # skinning 13,380 vertices (~7 ms a character) costs the same for every method
PARALLEL_MIN_CHARACTERS = 100
FPS = 60.0  # the characters' clocks advance by 1/60 s per benchmark frame


@dataclass(frozen=True)
class Case:
    """One thing to time: a clip in one variant."""

    animation: str
    method: str
    increment: int | None
    variant: str
    step: Callable[[np.ndarray], Any]  # poses all characters at the given times


def _reference_step(clip: Any) -> Callable[[np.ndarray], Any]:
    sample = (lambda t: clip.sample(t, method="nlerp")) if hasattr(clip, "resample") else clip.sample
    return lambda t: clip.skeleton.forward_kinematics(*sample(t))


def _naive_step(clip: SquadClip) -> Callable[[np.ndarray], Any]:
    """SQUAD from the keys every frame: tangents recomputed, then evaluated (what the thesis's Unity script did)."""
    return lambda t: clip.skeleton.forward_kinematics(*clip.sample(t, controls=clip.tangents()))


def _default_step(table: PoseTable, n: int, parallel: bool) -> Callable[[np.ndarray], Any]:
    buffers = CrowdBuffers.for_crowd(n, table.skeleton.n_joints)
    return lambda t: pose_crowd(table, t, buffers, parallel=parallel)


def _skinned(step: Callable[[np.ndarray], Any], mesh: Any) -> Callable[[np.ndarray], Any]:
    def run(t: np.ndarray) -> Any:
        out = step(t)
        return mesh.skin(mesh.skinning_matrices(out.rotations, out.positions))
    return run


def machine() -> dict[str, Any]:
    cpu = platform.processor() or ""
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next((line.split(":", 1)[1].strip() for line in f if line.startswith("model name")), cpu)
    except OSError:
        pass
    return {"cpu": cpu, "cores": os.cpu_count(), "python": platform.python_version(), "numpy": np.__version__,
            "numba": numba.__version__ if numba else None, "platform": platform.platform()}


def _time(cases: Sequence[Case], phases: np.ndarray, frames: int, warmup: int) -> dict[int, list[float]]:
    """Per case, the milliseconds of each timed frame; cases alternate within every frame."""
    times: dict[int, list[float]] = {i: [] for i in range(len(cases))}
    for frame in range(warmup + frames):
        t = phases + frame / FPS
        for i, case in enumerate(cases):
            start = time.perf_counter()
            case.step(t)
            elapsed = (time.perf_counter() - start) * 1000.0
            if frame >= warmup:
                times[i].append(elapsed)
    return times


def run(clips: Sequence[BuiltClip], characters: Sequence[int] = DEFAULT_CHARACTERS,
        stages: Sequence[str] = ("pose", "skin"), frames: int = 200, warmup: int = 20, seed: int = 2017,
        progress: Callable[[str], None] = lambda _m: None) -> dict[str, Any]:
    """Time every animation x method x variant x stage x crowd size; returns the results document."""
    rng = np.random.default_rng(seed)
    results: list[dict[str, Any]] = []
    memory: list[dict[str, Any]] = []
    animations = list(dict.fromkeys(c.animation for c in clips))
    tables: dict[str, PoseTable] = {}
    for c in clips:
        tables[c.id] = table_from_keyframes(c.clip) if c.method == "keyframe" else bake(c.clip)
        memory.append({"clip": c.id, "animation": c.animation, "method": c.method, "increment": c.increment,
                       "keys": int(c.key_times.size),
                       "stored_bytes": metrics.storage_bytes(c.key_times.size, c.character.skeleton.n_joints),
                       "runtime_table_bytes": tables[c.id].nbytes})
    started = time.perf_counter()
    for stage in stages:
        sizes = [n for n in characters if stage == "pose" or n <= SKIN_MAX_CHARACTERS]
        for n in sizes:
            for animation in animations:
                group = [c for c in clips if c.animation == animation]
                duration = max(tables[c.id].duration for c in group)
                phases = rng.uniform(0.0, 2 * duration, n)
                mesh = group[0].character.mesh
                rounds: list[tuple[int, list[Case]]] = [(1, [
                    Case(animation, c.method, c.increment, "default", _default_step(tables[c.id], n, False))
                    for c in group])]
                if stage == "pose" and n >= PARALLEL_MIN_CHARACTERS:
                    rounds.append((os.cpu_count() or 2, [
                        Case(animation, c.method, c.increment, "default", _default_step(tables[c.id], n, True))
                        for c in group]))
                if stage == "pose" and n <= REFERENCE_MAX_CHARACTERS:
                    ref = [Case(animation, c.method, c.increment, "reference", _reference_step(c.clip))
                           for c in group]
                    naive = [Case(animation, c.method, c.increment, "naive", _naive_step(c.clip))
                             for c in group if isinstance(c.clip, SquadClip)]
                    rounds.append((1, ref + naive))
                for threads, cases in rounds:
                    if stage == "skin":
                        cases = [Case(k.animation, k.method, k.increment, k.variant, _skinned(k.step, mesh))
                                 for k in cases]
                    timed = _time(cases, phases, frames, warmup)
                    for i, case in enumerate(cases):
                        ms = np.asarray(timed[i])
                        median = float(np.median(ms))
                        results.append({"animation": case.animation, "method": case.method,
                                        "increment": case.increment, "variant": case.variant, "stage": stage,
                                        "characters": n, "threads": threads, "median_ms": median,
                                        "p95_ms": float(np.percentile(ms, 95)), "fps": 1000.0 / median,
                                        "frames": len(ms)})
            progress(f"  {stage}: {n} characters done ({time.perf_counter() - started:.0f} s)")
    return {"machine": machine(), "settings": {"frames": frames, "warmup": warmup, "seed": seed,
                                               "characters": list(characters), "stages": list(stages),
                                               "clock_per_frame_s": 1 / FPS},
            "results": results, "memory": memory, "summary": summarize(results)}


def summarize(results: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """Hybrid / keyframe median ratios (stage pose, default variant, one thread) and the 10,000-character figure."""
    base = [r for r in results if r["stage"] == "pose" and r["variant"] == "default" and r["threads"] == 1]
    keyframe = {(r["animation"], r["characters"]): r["median_ms"] for r in base if r["method"] == "keyframe"}
    ratios = [{"animation": r["animation"], "increment": r["increment"], "characters": r["characters"],
               "ratio": r["median_ms"] / keyframe[(r["animation"], r["characters"])]}
              for r in base if r["method"] == "hybrid" and (r["animation"], r["characters"]) in keyframe]
    at_10 = [x["ratio"] for x in ratios if x["characters"] >= 10]
    biggest = max((r["characters"] for r in base), default=0)
    return {
        "ratios": ratios,
        "max_ratio_at_10_or_more": max(at_10) if at_10 else None,
        "largest_crowd": biggest,
        "largest_crowd_worst_ms": max((r["median_ms"] for r in base if r["characters"] == biggest), default=None),
    }


def series(results: Sequence[dict[str, Any]], stage: str = "pose") -> list[dict[str, Any]]:
    """Average over animations (and increments) of the median ms per frame, per method/variant, for plots."""
    out = []
    for name, keep in (
        ("keyframe", lambda r: r["method"] == "keyframe" and r["variant"] == "default"),
        ("hybrid", lambda r: r["method"] == "hybrid" and r["variant"] == "default"),
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


def write_plots(doc: dict[str, Any], out_dir: Any) -> list[Any]:
    """The thesis's figures 4.5 (average keyframe against average hybrid), 4.6 (per increment) and 4.7 (per
    animation), as FPS against characters on log axes; returns the files written."""
    from pathlib import Path

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    r = doc["results"]
    default = lambda m: (lambda x: x["method"] == m and x["variant"] == "default")  # noqa: E731
    figures = {
        "fps_average.svg": ("Average keyframe against average hybrid (pose, one thread)", _fps_lines(r, [
            ("keyframe", default("keyframe"), False), ("hybrid (baked)", default("hybrid"), False),
            ("keyframe, numpy reference", lambda x: x["method"] == "keyframe" and x["variant"] == "reference", True),
            ("hybrid, numpy reference", lambda x: x["method"] == "hybrid" and x["variant"] == "reference", True),
            ("hybrid, naive SQUAD", lambda x: x["method"] == "hybrid" and x["variant"] == "naive", True)])),
        "fps_increment.svg": ("Per increment (pose, one thread)", _fps_lines(r, [
            ("keyframe", default("keyframe"), False)] + [
            (f"hybrid increment {i}", lambda x, i=i: default("hybrid")(x) and x["increment"] == i, False)
            for i in sorted({x["increment"] for x in r if x["method"] == "hybrid"})])),
        "fps_animation.svg": ("Per animation (pose, one thread)", _fps_lines(r, [
            (f"{a} {m}", lambda x, a=a, m=m: default(m)(x) and x["animation"] == a, m == "keyframe")
            for a in dict.fromkeys(x["animation"] for x in r) for m in ("keyframe", "hybrid")])),
    }
    written = []
    for name, (title, lines) in figures.items():
        if lines:
            path = out / name
            path.write_text(svg_chart(lines, title, "characters", "frames per second"), encoding="utf-8")
            written.append(path)
    return written
