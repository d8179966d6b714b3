"""``animstudy bench``: pose evaluation of crowds and render speed."""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path
from typing import Any

from anim_core.bench import suite as benchmark
from anim_core.bench.blend import format_blend
from anim_core.bench.suite import DEFAULT_CHARACTERS, VARIANTS
from anim_core.clips.build import ConfigError
from server.assets import AssetError
from server.clipset.build import build_clip_set
from server.clipset.config import load_config
from server.clipset.manifest import write_clip_set
from server.config import Settings
from server.errors import MediaError
from server.media.build import render_tasks, run_on_dask
from server.media.plan import plan
from server.media.scene import RenderSettings
from server.studies.service import clip_set_index, required_pairs
from server.studies.studyfile import thesis_study

from .common import fail


def bench_render(settings: Settings, width: int, height: int, animations: list[str] | None) -> int:
    """Frames per second of rendering the default study's videos on a real Dask cluster (a local scheduler and
    worker processes) of 1 and then 2 workers, the same work each time, and the ratio."""


    render_settings = RenderSettings(width=width, height=height)
    with tempfile.TemporaryDirectory(prefix="animstudy-bench-render-") as tmp:
        clips_dir = Path(tmp) / "clips"
        try:
            if (settings.clips_dir / "manifest.json").is_file():
                clips_dir = settings.clips_dir
            else:
                print("building the clip set", flush=True)
                write_clip_set(build_clip_set(settings.data), clips_dir)
            pairs = required_pairs(thesis_study().design, clip_set_index(clips_dir))
            fps = {}
            for workers in (1, 2):
                out = Path(tmp) / f"media-{workers}"
                out.mkdir()
                p = plan(settings.data, clips_dir, out, render_settings, settings.secret, pairs, animations)
                frames = sum(j.n_frames for j in p.jobs)
                tasks = render_tasks(p, workers)  # as run_on_dask cuts it on a local cluster of `workers`
                # A per-video task renders its clips itself: the clip shown in several pairs once per pair.
                print(f"{workers} worker(s): {sum(len(j.outputs) for j in p.jobs)} videos in {len(tasks)} tasks, "
                      f"{frames} frames of the study, {sum(t.n_frames for t in tasks)} frames rendered by the "
                      f"tasks, at {width}x{height}", flush=True)
                started = time.perf_counter()
                run_on_dask(p, out, None, workers, lambda m: print(m, flush=True))
                seconds = time.perf_counter() - started
                fps[workers] = frames / seconds
                print(f"{workers} worker(s): {seconds:.1f} s, {fps[workers]:.1f} frames/s (cluster start "
                      "included)", flush=True)
        except (AssetError, MediaError) as exc:
            return fail(str(exc))
    print(f"render: 1 worker {fps[1]:.1f} frames/s, 2 workers {fps[2]:.1f} frames/s, ratio {fps[2] / fps[1]:.2f} "
          f"(on {os.cpu_count()} cores; load average {os.getloadavg()[0]:.1f})", flush=True)
    return 0


def bench(settings: Settings, json_path: Path, characters: list[int], stages: list[str], frames: int,
          variants: list[str], config: Path | None = None) -> int:
    """Run the performance benchmark on the clip set of ``config`` (default: the built-in one); write JSON (for
    the dashboard too) and the plots beside it."""
    # One thread for numpy/BLAS in the main figures (the compiled kernel's threads are a separate figure).
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = "1"

    started = time.perf_counter()
    try:
        print(f"building the clip set{f' of {config}' if config else ''}", flush=True)
        clips = build_clip_set(settings.data, load_config(config) if config else None)
    except (AssetError, ConfigError) as exc:
        return fail(str(exc))
    print(f"building the runtimes and measuring memory and accuracy ({', '.join(variants)})", flush=True)
    doc = benchmark.run(clips, characters, stages, frames=frames, variants=variants,
                        progress=lambda m: print(m, flush=True))
    doc["series"] = benchmark.series(doc["results"])
    doc["x_label"], doc["y_label"] = "characters", "ms per frame (pose, one thread)"
    try:
        json_path.parent.mkdir(parents=True, exist_ok=True)
        json_path.write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")
        plots = benchmark.write_plots(doc, json_path.parent)
    except OSError as exc:
        return fail(f"cannot write the results: {exc}")
    _print_bench(doc)
    print(format_blend(doc["results"]), end="")
    print(f"results: {json_path}; plots: {', '.join(p.name for p in plots)}; "
          f"{time.perf_counter() - started:.0f} s in all")
    return 0


def _print_bench(doc: dict[str, Any]) -> None:
    """Per clip (every condition) and crowd size the median ms per frame and its ratio to the keyframe clip of the
    same animation, then bytes and errors per clip, then the goals' figures."""
    variant = "keys" if "keys" in doc["settings"]["variants"] else doc["settings"]["variants"][0]
    rows = [r for r in doc["results"] if r["stage"] == "pose" and r["variant"] == variant and r["threads"] == 1]
    width = max([16, *(len(m["clip"]) + 1 for m in doc["memory"])])
    if rows:
        ns = sorted({r["characters"] for r in rows})
        keyframe = {(r["animation"], r["characters"]): r["median_ms"] for r in rows if r["method"] == "keyframe"}
        print(f"\nmedian ms per frame (÷ the keyframe clip's, same rounds), variant {variant}, pose, one thread")
        print(f"{'clip':{width}}" + "".join(f"{n:>15}" for n in ns))
        for clip in dict.fromkeys((r["animation"], r["condition"]) for r in rows):
            by_n = {r["characters"]: r["median_ms"] for r in rows if (r["animation"], r["condition"]) == clip}
            cells = [(f"{by_n[n]:.4g}" + ("" if (clip[0], n) not in keyframe else
                                          f" ({by_n[n] / keyframe[(clip[0], n)]:.2f})")) if n in by_n else ""
                     for n in ns]
            print(f"{clip[0] + '-' + clip[1]:{width}}" + "".join(f"{c:>15}" for c in cells))
    variants = list(dict.fromkeys(m["variant"] for m in doc["memory"]))
    mem = {(m["clip"], m["variant"]): m["runtime_bytes"] for m in doc["memory"]}
    err = {(a["clip"], a["variant"]): a["max_error_deg"] for a in doc["accuracy"]}
    stored = {m["clip"]: m["stored_bytes"] for m in doc["memory"]}
    main = [v for v in variants if not v.startswith("keys-")]
    print("\nruntime bytes (stored keys first) and largest global-rotation error in degrees, per clip and variant")
    print(f"{'clip':{width}}{'stored':>8}" + "".join(f"{v:>10}" for v in main)
          + "".join(f"{'err ' + v:>14}" for v in main))
    for clip in stored:
        print(f"{clip:{width}}{stored[clip]:>8}" + "".join(f"{mem.get((clip, v), ''):>10}" for v in main)
              + "".join(f"{err[(clip, v)]:>14.4f}" if (clip, v) in err else f"{'':>14}" for v in main))
    lods = [v for v in variants if v.startswith("keys-")]
    if lods:
        print("\nLOD variants of keys: largest error in degrees per clip")
        print(f"{'clip':{width}}" + "".join(f"{v:>18}" for v in lods))
        for clip in stored:
            print(f"{clip:{width}}" + "".join(f"{err.get((clip, v), float('nan')):>18.3f}" for v in lods))
    s = doc["summary"]
    print()
    for label, value, unit in (
        ("worst hybrid/keyframe ratio at >= 10 characters (keys)", s["max_ratio_at_10_or_more"], ""),
        ("median hybrid/keyframe ratio at >= 10 characters (keys)", s["median_ratio_at_10_or_more"], ""),
        (f"{s['largest_crowd']} characters, worst median (keys, one thread)", s["largest_crowd_worst_ms"], " ms"),
        (f"speed-up on {s['parallel_threads']} threads at {s['largest_crowd']} characters, min / median",
         None if s["parallel_speedup_min"] is None else f"{s['parallel_speedup_min']:.2f} / "
         f"{s['parallel_speedup_median']:.2f}", ""),
        ("largest increment-0 hybrid runtime bytes / keyframe's (keys)", s["max_memory_ratio_increment_0"], ""),
        ("largest hybrid error (keys), degrees", s["max_hybrid_error_deg"], ""),
    ):
        shown = "n/a" if value is None else (f"{value:.3f}" if isinstance(value, float) else value)
        print(f"{label}: {shown}{unit}")


def run(settings: Settings, args: argparse.Namespace) -> int:
    """``animstudy bench [crowd|render]``, the defaults of ``--quick`` filled in."""
    if args.what == "render":
        return bench_render(settings, max(16, args.width), max(16, args.height), args.animations)

    quick = args.quick
    return bench(settings, args.json or settings.benchmark_path,
                 args.characters or ([10, 1000] if quick else list(DEFAULT_CHARACTERS)),
                 args.stages or (["pose"] if quick else ["pose", "skin"]),
                 max(1, args.frames or (50 if quick else 200)),
                 args.variants or (["keys"] if quick else list(VARIANTS)), args.config)
