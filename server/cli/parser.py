"""``animstudy`` command line."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path

from . import thresholds as threshold_commands
from .common import CLI_FRAME_JOINTS, even, positive

QUICK_BENCH = "--characters 10,1000 --stages pose --frames 50 --variants keys"


def _variants(text: str) -> list[str]:
    from anim_core.bench.suite import VARIANTS

    chosen = [v.strip() for v in text.split(",") if v.strip()]
    if not chosen or any(v not in VARIANTS for v in chosen):
        raise argparse.ArgumentTypeError(f"variants are {', '.join(VARIANTS)} (comma-separated), got {text!r}")
    return list(dict.fromkeys(chosen))


def _int_list(minimum: int, example: str) -> Callable[[str], list[int]]:
    """An argparse type: comma-separated integers, each at least ``minimum``."""
    def parse(text: str) -> list[int]:
        try:
            values = [int(v) for v in text.split(",") if v.strip()]
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected comma-separated numbers like {example}, got {text!r}") from None
        if not values or any(v < minimum for v in values):
            raise argparse.ArgumentTypeError(f"expected comma-separated numbers ≥ {minimum} like {example}, "
                                             f"got {text!r}")
        return values
    return parse


def _stages(text: str) -> list[str]:
    stages = [s.strip() for s in text.split(",") if s.strip()]
    if not stages or any(s not in ("pose", "skin", "blend") for s in stages):
        raise argparse.ArgumentTypeError(f"stages are pose, skin and blend, got {text!r}")
    return stages


def _source_options(parser: argparse.ArgumentParser) -> None:
    """--mapping, --units and --up of ``clips inspect`` and ``clips convert``."""
    parser.add_argument("--mapping", type=Path, default=None,
                        help="explicit joint mapping (.toml or .json: character joint = file joint)")
    parser.add_argument("--units", choices=["m", "cm", "mm", "inch", "cmu"], default=None,
                        help="length unit of the file (default: detected from the skeleton's height)")
    parser.add_argument("--up", choices=["y", "z"], default=None, help="up axis of the file (default: detected)")
    parser.add_argument("--max-frame-joints", type=int, default=None, metavar="N",
                        help=f"read at most N frames × joints (default: {CLI_FRAME_JOINTS}, or more for a large "
                        "file: a file of joints without channels can ask for gigabytes)")


def loadtest_parser(add_help: bool = True) -> argparse.ArgumentParser:
    """The options of ``animstudy loadtest`` (defined here, not in server/loadtest.py, whose imports would slow
    every command's start)."""
    p = argparse.ArgumentParser(prog="animstudy loadtest", add_help=add_help,
                                description="Load, crash and outage test of the participant API: N simulated "
                                "participants against a fresh server and database; exits non-zero if any "
                                "acknowledged vote was lost or doubled.")
    p.add_argument("--database", choices=["sqlite", "postgresql"], default="sqlite",
                   help="a fresh database of this kind (PostgreSQL: the one of --pg-url, emptied first)")
    p.add_argument("--participants", type=int, default=200, help="simulated participants, 16 votes each")
    p.add_argument("--workers", type=int, default=2, help="uvicorn worker processes of the server")
    p.add_argument("--concurrency", type=int, default=100, help="participants in progress at a time")
    p.add_argument("--pause-ms", type=float, default=0.0, help="mean think time before each vote")
    p.add_argument("--ramp-s", type=float, default=0.0,
                   help="spread the participants' arrivals over this many seconds (default: all at once)")
    p.add_argument("--crash-at", type=float, default=None, help="SIGKILL the server at this share of the votes")
    p.add_argument("--outage-at", type=float, default=None, help="stop PostgreSQL at this share of the votes")
    p.add_argument("--outage-s", type=float, default=5.0, help="seconds PostgreSQL stays stopped")
    p.add_argument("--time-limit", type=float, default=300.0, help="seconds before the run gives up")
    p.add_argument("--pg-url", default=None, help="PostgreSQL database to use, its schema dropped (default: "
                   "database animstudy_load of the local server, as user postgres)")
    p.add_argument("--json", type=Path, default=None, help="also write the report as JSON to this file")
    return p


def build_parser() -> argparse.ArgumentParser:
    """The whole command line, every subcommand and option (the docs site's CLI reference is generated from it)."""
    parser = argparse.ArgumentParser(prog="animstudy", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("inspect", help="summarize the motion-capture files of the data directory")
    loadtest = loadtest_parser(add_help=False)
    sub.add_parser("loadtest", help="load, crash and outage test of the participant API", parents=[loadtest],
                   description=loadtest.description)
    _clips(sub)
    _render_and_serve(sub)
    _study(sub)
    _gc_and_bench(sub)
    return parser


def _clips(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    clips = sub.add_parser("clips", help="the clip set (keyframe and hybrid clips with motion metrics)")
    clips_sub = clips.add_subparsers(dest="clips_command", required=True)
    build = clips_sub.add_parser("build", help="build the clip set from the data directory")
    build.add_argument("--out", type=Path, default=None, help="output folder (default: <var dir>/clips)")
    build.add_argument("--config", type=Path, default=None, help="clip set TOML (default: the built-in one)")
    cinspect = clips_sub.add_parser("inspect", help="what a BVH/glTF motion file holds and how it maps onto the "
                                                   "character (joints, mapping, units, contacts, suggested kind)")
    cinspect.add_argument("file", type=Path, help=".bvh, .bvh.gz, .glb or .gltf file")
    _source_options(cinspect)
    convert = clips_sub.add_parser("convert", help="a BVH/glTF motion retargeted onto the character, written as "
                                                   ".glb/.gltf (character + animation) or .bvh")
    convert.add_argument("file", type=Path, help=".bvh, .bvh.gz, .glb or .gltf file (a glTF's first animation)")
    convert.add_argument("out", type=Path, help="output .glb, .gltf, .bvh or .bvh.gz")
    _source_options(convert)
    export = clips_sub.add_parser("export", help="one clip of a built clip set on the character, written as "
                                                 ".glb/.gltf (character + animation) or .bvh")
    export.add_argument("clip", help="clip id, <animation>-<condition> (see the clip set's manifest.json)")
    export.add_argument("--clips", type=Path, default=None, help="clip set folder (default: <var dir>/clips)")
    export.add_argument("--out", type=Path, required=True, help="output .glb, .gltf, .bvh or .bvh.gz")


def _render_and_serve(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    rend = sub.add_parser("render", help="pre-render the compared pairs (and their clips) into blind videos")
    rend.add_argument("--out", type=Path, default=None, help="video folder (default: <var dir>/media)")
    rend.add_argument("--clips", type=Path, default=None, help="clip set folder (default: <var dir>/clips)")
    rend.add_argument("--workers", type=int, default=2, help="worker processes (default: 2)")
    rend.add_argument("--study", type=Path, action="append", default=None,
                      help="study file whose pairs to render, may be repeated (default: studies/thesis.toml for the "
                           "server's clip set; another --clips set needs --study or --every-clip); the pairs of "
                           "the studies in the database are kept too")
    rend.add_argument("--every-clip", action="store_true",
                      help="also a video of every clip of the clip set (default: of the clips the pairs show)")
    rend.add_argument("--width", type=even, default=640)
    rend.add_argument("--height", type=even, default=480)
    rend.add_argument("--no-shadows", action="store_true")
    srv = sub.add_parser("serve", help="migrate the database, prepare the default study if needed, and serve")
    srv.add_argument("--host", default="127.0.0.1")
    srv.add_argument("--port", type=int, default=8000)
    srv.add_argument("--workers", type=int, default=1, help="uvicorn worker processes (default: 1)")
    researcher = sub.add_parser("researcher", help="researcher accounts")
    researcher_sub = researcher.add_subparsers(dest="researcher_command", required=True)
    rc = researcher_sub.add_parser("create", help="create a researcher account")
    rc.add_argument("--email", required=True)
    given = rc.add_mutually_exclusive_group()
    given.add_argument("--password-stdin", action="store_true",
                       help="read the password from standard input (its first line), e.g. from a password manager")
    given.add_argument("--password", default=None, help="the password (visible to every user of the machine in the "
                       "process list: prefer the prompt or --password-stdin)")
    rc.add_argument("--admin", action="store_true", help="may see and manage every study, not only their own")


def _study(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    st = sub.add_parser("study", help="study files and studies: schema, validate, create, list, open, close, export")
    st_sub = st.add_subparsers(dest="study_command", required=True)
    st_sub.add_parser("schema", help="print the JSON Schema of study files")
    sv = st_sub.add_parser("validate", help="check a study file (every error with its field and line)")
    sv.add_argument("file", type=Path)
    sc = st_sub.add_parser("create", help="build the clips and render the videos a study file needs (what is "
                           "missing; its [clips] set or the server's clip set) and create it as a draft")
    sc.add_argument("file", type=Path)
    sc.add_argument("--open", action="store_true", help="open it for participants at once")
    sc.add_argument("--owner", default=None, help="e-mail of the researcher who owns it (default: none; admins "
                    "manage it)")
    sc.add_argument("--width", type=even, default=None, help="video width when none were rendered before (640)")
    sc.add_argument("--height", type=even, default=None, help="video height (480)")
    sc.add_argument("--no-shadows", action="store_true")
    st_sub.add_parser("list", help="every study with its state and counts")
    for name in ("open", "close"):
        so = st_sub.add_parser(name, help=f"{name} a study for participants")
        so.add_argument("slug")
    sa = st_sub.add_parser("export-archive", help="one file with the study file, its pinned stimulus set and its "
                           "videos, to rerun the study on another server")
    sa.add_argument("slug")
    sa.add_argument("--out", type=Path, default=None, help="archive file (default: <slug>.animstudy.zip)")
    si = st_sub.add_parser("import-archive", help="recreate a study from its archive (same stimuli, byte for byte)")
    si.add_argument("file", type=Path)
    si.add_argument("--owner", default=None, help="e-mail of the researcher who owns it (default: none)")
    si.add_argument("--open", action="store_true", help="open it for participants at once")
    si.add_argument("--max-mib", type=positive, default=None, help="the most its files may take in all, in MiB "
                    "(default 8192; each file at most 512)")
    sm = st_sub.add_parser("simulate", help="simulated observers through a study file's design: scale error and "
                           "rank correlation (docs/designs.md)")
    sm.add_argument("file", type=Path)
    sm.add_argument("--participants", type=positive, required=True)
    sm.add_argument("--truth", type=Path, default=None, help="TOML or JSON table: condition = true scale value "
                    "(logit units); default: the design's conditions evenly spaced over 0..2.5 in their order")
    sm.add_argument("--seeds", type=positive, default=20, help="simulated studies (default 20)")
    sp = st_sub.add_parser("plan", help="participants needed to detect a difference from the reference, by "
                           "simulation (docs/designs.md)")
    sp.add_argument("file", type=Path)
    sp.add_argument("--effect", type=float, default=None, help="the difference to detect, logit units of the "
                    "scale (every condition that far above the reference); required but for threshold designs")
    sp.add_argument("--power", type=float, default=0.8)
    sp.add_argument("--seeds", type=positive, default=100, help="simulated studies per participant count")
    threshold_commands.extend_simulate_plan(sm, sp)  # issue 38: threshold designs' options and commands
    threshold_commands.add_parsers(st_sub, positive)
    se = st_sub.add_parser("export", help="a study's votes, one row per vote (see the data dictionary)")
    se.add_argument("slug")
    se.add_argument("--format", choices=("csv", "json", "sureal", "pwcmp"), default="csv",
                    help="csv/json: one row per vote; sureal: a sureal dataset (JSON); pwcmp: pairwise CSV")
    se.add_argument("--out", type=Path, default=None, help="file to write (default: standard output)")


def _gc_and_bench(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    gcp = sub.add_parser("gc", help="delete the videos no study's stimulus set (and no render manifest) uses and "
                                    "the clip files no clip set's manifest names")
    gcp.add_argument("--dry-run", action="store_true", help="list them, delete nothing")
    bn = sub.add_parser("bench", help="time pose evaluation of crowds, keyframe against every other condition "
                                      "(`bench render`: render frames per second on 1 and 2 Dask workers)")
    bn.add_argument("what", nargs="?", choices=["crowd", "render"], default="crowd",
                    help="crowd (default): pose evaluation; render: the default study's videos on a local Dask "
                         "cluster of 1 and then 2 workers")
    bn.add_argument("--width", type=int, default=160, help="bench render: video width (default: 160)")
    bn.add_argument("--height", type=int, default=120, help="bench render: video height (default: 120)")
    bn.add_argument("--animations", type=lambda v: [a for a in v.split(",") if a], default=None,
                    help="bench render: only these animations, comma-separated (default: all)")
    bn.add_argument("--json", type=Path, default=None, help="results file (default: <var dir>/benchmark/results.json)")
    bn.add_argument("--config", type=Path, default=None,
                    help="clip-set TOML whose clips to time (default: the built-in one), e.g. "
                         "server/clipset/conditions16.toml")
    bn.add_argument("--quick", action="store_true",
                    help=f"short run: {QUICK_BENCH} unless given")
    bn.add_argument("--characters", type=_int_list(1, "10,200"), default=None, help="crowd sizes, e.g. 10,200,10000")
    bn.add_argument("--stages", type=_stages, default=None,
                    help="pose, skin (default: both), blend (blending jobs, crossfade with held feet)")
    bn.add_argument("--frames", type=int, default=None, help="timed frames per measurement (default: 200)")
    bn.add_argument("--variants", type=_variants, default=None,
                    help="comma-separated: keys, baked, reference, naive (default: all)")
