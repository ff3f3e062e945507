"""``groundstation bench ...``: the options and entry of every benchmark.

Each command is a pair ``add_NAME_arguments(parser)`` / ``run_NAME(args) -> int``; the
measurements themselves live in ``groundstation.bench.NAME`` (pure generators, fits and
scores) and are called from here.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import tempfile
import time
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from groundstation.bench import detector as detector_bench
from groundstation.bench import paper2d as paper2d_bench
from groundstation.bench import pareto as pareto_bench
from groundstation.bench import scenes3d, shapes2d
from groundstation.bench import sessions as sessions_bench
from groundstation.bench import speed as speed_bench
from groundstation.bench import stability as stability_bench
from groundstation.errors import ConfigError, InputDataError

# ------------------------------ bench paper2d


def add_paper2d_arguments(parser: argparse.ArgumentParser) -> None:
    """Command-line options of ``groundstation bench paper2d``."""
    parser.add_argument(
        "--seeds", type=int, default=None, help="runs per shape (default 50; 3 with --quick)"
    )
    parser.add_argument(
        "--shapes",
        default=",".join(shapes2d.SHAPES),
        help="comma-separated subset of square,circle,cross",
    )
    parser.add_argument("--out", default="results/paper2d", help="output folder (created)")
    parser.add_argument(
        "--quick", action="store_true", help="3 seeds and a 0.04 m grid (about a minute)"
    )
    parser.add_argument(
        "--prior-mean", type=float, default=0.0, help="GP prior mean mu0 (paper: 0)"
    )
    parser.add_argument("--jobs", type=int, default=2, help="worker processes (1 BLAS thread each)")


def run_paper2d(args: argparse.Namespace) -> int:
    """Run the bench, print the tables, write summary.md, results.json and the figures."""
    shapes = [x.strip() for x in args.shapes.split(",") if x.strip()]
    for name in shapes:
        shapes2d.make_shape(name)  # raises ConfigError naming a bad shape
    seeds = args.seeds if args.seeds is not None else (3 if args.quick else 50)
    if seeds < 1 or args.jobs < 1:
        raise ConfigError(f"--seeds ({seeds}) and --jobs ({args.jobs}) must be >= 1")
    if not math.isfinite(args.prior_mean):
        raise ConfigError(f"--prior-mean must be a finite number, got {args.prior_mean}")
    s = paper2d_bench.BenchSettings(
        spacing=0.04 if args.quick else 0.02, prior_mean=args.prior_mean
    )
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    tasks = [(shape, seed, seed == 0) for shape in shapes for seed in range(seeds)]
    t0 = time.perf_counter()
    runs = paper2d_bench._run_all(tasks, s, args.jobs)
    wall = time.perf_counter() - t0
    for r in runs:
        if "fields" in r:
            paper2d_bench.plot_shape(r, out / f"fig6_{r['shape']}.png", s)
            del r["fields"]
    table = paper2d_bench.summarize(runs)
    text = (
        paper2d_bench.render_summary(table, s, seeds)
        + f"\nWall time {wall:.1f} s with --jobs {args.jobs}.\n"
    )
    (out / "summary.md").write_text(text)
    payload = {"settings": dataclasses.asdict(s), "seeds": seeds, "shapes": shapes,
               "jobs": args.jobs, "wall_s": wall, "versions": paper2d_bench._versions(),
               "summary": table, "runs": runs}  # fmt: skip
    (out / "results.json").write_text(json.dumps(payload, indent=1, allow_nan=False))
    print(text)
    print(f"wrote {out / 'summary.md'}, {out / 'results.json'} and {len(shapes)} figure(s)")
    return 0


# ------------------------------ bench detector


def add_detector_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``groundstation bench detector``."""
    parser.add_argument("--out", default="results/bench_detector", help="output folder")
    parser.add_argument(
        "--thresholds",
        help="thresholds a0 in G, comma-separated "
        "(default 0.3,...,1.2 by 0.1,1.5,2,2.5; --quick 0.4,0.6,0.8)",
    )
    parser.add_argument(
        "--filters",
        help="filters: moving_average[:window_s], "
        f"butterworth2[:cutoff_hz], none (default {','.join(detector_bench.DEFAULT_FILTERS)}; "
        "--quick: moving_average,butterworth2,none with the configured "
        "parameters)",
    )
    parser.add_argument("--seeds", type=int, help="SITL seeds per scene (default 3; --quick 1)")
    parser.add_argument(
        "--duration",
        type=float,
        help="SITL seconds per session (default: until the scripted pilot is done)",
    )
    parser.add_argument(
        "--scenes", help=f"SITL scenes (default {','.join(detector_bench.SCENES)}; --quick pillar)"
    )
    parser.add_argument(
        "--pilots", default=",".join(detector_bench.PILOTS), help="SITL pilot scripts"
    )
    parser.add_argument(
        "--paths",
        help="aggressive_flight paths, or 'none' "
        f"(default {','.join(detector_bench.REAL_PATHS)}; --quick Horizontal/path_1)",
    )
    parser.add_argument(
        "--files",
        help=f"IMU files per path (default {','.join(detector_bench.REAL_FILES)}; "
        "--quick IMU_1.csv)",
    )
    parser.add_argument("--tolerance", type=float, default=0.15, help="event matching +-s")
    parser.add_argument("--min-recall", type=float, default=0.95, help="recall to keep")
    parser.add_argument("--quick", action="store_true", help="one path, one seed, few thresholds")
    parser.add_argument("--config", help="TOML config (its [contact] is the base/default)")
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="config override, e.g. contact.refractory_s=0.3",
    )


def _csv_list(text: str | None, default: Sequence[str]) -> list[str]:
    return [v.strip() for v in (text.split(",") if text else default) if v.strip()]


def run_detector(args: argparse.Namespace) -> int:
    """Run the sweep, print the table and recommendation, write PNG / md / json into ``--out``."""
    from tqdm import tqdm

    from groundstation.config import load_config

    q = bool(args.quick)
    base = load_config(args.config, args.set).contact
    thresholds = (
        detector_bench._floats(args.thresholds)
        if args.thresholds
        else ([0.4, 0.6, 0.8] if q else list(detector_bench.DEFAULT_THRESHOLDS))
    )
    # The configured default is always measured, so the table can mark it.
    thresholds = sorted(set(thresholds) | {base.threshold_g})
    quick_filters = ("moving_average", "butterworth2", "none")
    filters = _csv_list(args.filters, quick_filters if q else detector_bench.DEFAULT_FILTERS)
    specs = [detector_bench.FilterSpec.parse(f, base) for f in filters]
    seeds = args.seeds if args.seeds is not None else (1 if q else 3)
    scenes = _csv_list(args.scenes, ("pillar",) if q else detector_bench.SCENES)
    pilots = _csv_list(args.pilots, detector_bench.PILOTS)
    paths = _csv_list(args.paths, ("Horizontal/path_1",) if q else detector_bench.REAL_PATHS)
    files = _csv_list(args.files, ("IMU_1.csv",) if q else detector_bench.REAL_FILES)
    if paths == ["none"]:
        paths = []
    if seeds < 1:
        raise detector_bench.BenchDataError(f"--seeds {seeds}: need at least 1")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    err = sys.stderr

    real: list[detector_bench.Trace] = []
    if paths:
        root = detector_bench.external_data_root()
        if not (root / "aggressive_flight").is_dir():
            raise detector_bench.BenchDataError(
                f"external data not found at {root / 'aggressive_flight'}",
                hint="set GS_EXTERNAL_DATA to the folder holding aggressive_flight/ "
                "(see ../shared/external_data/SOURCES.md), or pass --paths none",
            )
        print(detector_bench.ATTRIBUTION, file=err)
        with tempfile.TemporaryDirectory(prefix="bench_detector_") as tmp:
            jobs = [(p, f) for p in paths for f in files]
            for p, f in tqdm(jobs, desc="real flights (import + replay)", file=err):
                real.append(detector_bench.load_real_flight(root, p, f, Path(tmp)))
    else:
        print("real flights skipped (--paths none): no false-contact rate measured", file=err)
    sessions = [(s, p, k) for s in scenes for p in pilots for k in range(seeds)]
    sitl = [
        detector_bench.simulate_session(s, p, k, args.duration)
        for s, p, k in tqdm(sessions, desc="SITL sessions", file=err)
    ]
    with tqdm(total=len(specs) * len(thresholds), desc="sweep", file=err) as bar:
        rows, peaks = detector_bench.sweep(
            real,
            sitl,
            specs,
            thresholds,
            base,
            args.tolerance,
            detector_bench._surface_distance(),
            bar,
        )
    rec = detector_bench.recommend(rows, args.min_recall)

    real_min = sum(t.duration_s for t in real) / 60
    sitl_min = sum(t.duration_s for t in sitl) / 60
    n_touch = sum(e.kind == "touch" for t in sitl for e in t.truth)
    n_slow = sum(e.kind == "slow_touch" for t in sitl for e in t.truth)
    n_gust = sum(e.kind == "gust" for t in sitl for e in t.truth)
    command = "groundstation bench detector " + " ".join(sys.argv[3:] if len(sys.argv) > 3 else [])
    summary = (
        f"real flights: {len(real)} traces, {real_min:.2f} min ({', '.join(t.name for t in real)})"
        f"\nSITL: {len(sitl)} sessions ({','.join(scenes)} x {','.join(pilots)} x {seeds} seeds), "
        f"{sitl_min:.2f} min, {n_touch} touches, {n_slow} slow touches, {n_gust} gusts"
        f"\nbase settings: {base}\nmatching tolerance +-{args.tolerance} s, "
        f"minimum recall {args.min_recall}"
    )
    md = "\n\n".join(
        [
            "# Contact detector: false contacts on real flights vs recall on simulated touches",
            f"Command: `{command.strip()}`",
            summary.replace("\n", "  \n"),
            "FP/min: detected contact events per minute of real (contact-free) flight; % above: "
            "samples whose filtered |a| exceeds a0. Recall / gusts: fraction of SITL truth events "
            f"overlapped by a detection (+-{args.tolerance} s). Localisation: paper's cylinder "
            "rule at the event's peak, vs the truth contact point and vs the true surface. "
            f"Warm-up: events within {detector_bench.WARMUP_S} s of a trace's start (the filters "
            "output the raw first sample). Margin: min(touch peak p5 / a0, a0 / real max after "
            "warm-up).",
            detector_bench.table_markdown(rows),
            "## Filtered |a| peaks per filter",
            detector_bench.peaks_markdown(peaks),
            "## Recommendation",
            rec["text"].replace("\n", "  \n"),
            f"Attribution: {detector_bench.ATTRIBUTION}",
        ]
    )
    (out / "detector.md").write_text(md + "\n")
    detector_bench.plot(rows, out / "detector.png", args.min_recall)
    payload = {
        "attribution": detector_bench.ATTRIBUTION,
        "command": command.strip(),
        "base_settings": dataclasses.asdict(base),
        "thresholds": thresholds,
        "filters": [s.label for s in specs],
        "real_traces": [
            {
                "name": t.name,
                "minutes": t.duration_s / 60,
                "samples": int(t.t_ns.size),
                "dropped": t.dropped,
            }
            for t in real
        ],
        "sitl_sessions": [
            {
                "name": t.name,
                "minutes": t.duration_s / 60,
                "dropped": t.dropped,
                "truth": {
                    k: sum(e.kind == k for e in t.truth)
                    for k in ("touch", "slow_touch", "gust", "ground")
                },
            }
            for t in sitl
        ],
        "points": rows,
        "peaks": peaks,
        "recommendation": {
            "text": rec["text"],
            "default_ok": rec["default_ok"],
            "best": None
            if rec["best"] is None
            else {
                k: rec["best"][k]
                for k in ("filter", "filter_name", "window_s", "cutoff_hz", "threshold_g")
            },
        },
    }
    (out / "results.json").write_text(
        json.dumps(detector_bench._jsonable(payload), indent=1, allow_nan=False)
    )
    print(detector_bench.table_markdown(rows))
    print()
    print(detector_bench.peaks_markdown(peaks))
    print()
    print(summary)
    print(rec["text"])
    print(detector_bench.ATTRIBUTION)
    print(f"wrote {out / 'detector.png'}, {out / 'detector.md'}, {out / 'results.json'}")
    return 0


# ------------------------------ bench pareto


def add_pareto_arguments(parser: argparse.ArgumentParser) -> None:
    """Command-line options of ``groundstation bench pareto``."""
    parser.add_argument("--out", default="results/pareto", help="output folder (created)")
    parser.add_argument(
        "--quick",
        action="store_true",
        help="CI size: circle only, n ~ 700 in 3D, coarse grids, 5-min session",
    )
    parser.add_argument(
        "--scenes",
        default="2d,paper3d,session40",
        help="comma-separated subset of 2d, paper3d, session40",
    )
    parser.add_argument(
        "--refit-every",
        type=float,
        default=None,
        help="session refit interval, s (120; 60 with --quick)",
    )
    parser.add_argument("--seed", type=int, default=0, help="data seed")


def run_pareto(args: argparse.Namespace) -> int:
    """Run every point, print the tables, write the charts, pareto.md and results.json."""
    from threadpoolctl import threadpool_limits
    from tqdm import tqdm

    scenes = [x.strip() for x in args.scenes.split(",") if x.strip()]
    for sc in scenes:
        if sc not in ("2d", "paper3d", "session40"):
            raise ConfigError(f"unknown scene {sc!r}", hint="choose from 2d, paper3d, session40")
    every = args.refit_every if args.refit_every is not None else (60.0 if args.quick else 120.0)
    if not every > 0:
        raise ConfigError(f"--refit-every must be > 0 s, got {every}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    core = pareto_bench._core()
    import scipy.linalg  # noqa: F401  (load every BLAS before limiting it)

    import groundstation.mapping.robust  # noqa: F401

    jobs: list[tuple[str, pareto_bench.BenchScene, list[pareto_bench.PointSpec]]] = []
    if "2d" in scenes:
        shapes = ("circle",) if args.quick else shapes2d.SHAPES
        for sh in shapes:
            jobs.append(
                (
                    "2d",
                    pareto_bench.scene_2d(sh, args.seed),
                    pareto_bench.method_specs(2, args.quick),
                )
            )
    if "paper3d" in scenes:
        kw = dict(n_contacts=300, n_external=150) if args.quick else {}
        jobs.append(
            (
                "paper3d",
                pareto_bench.scene_3d(scenes3d.paper3d(args.seed, **kw)),
                pareto_bench.method_specs(3, args.quick),
            )
        )
    session = None
    if "session40" in scenes:
        session = scenes3d.session40(args.seed, duration_s=300.0 if args.quick else 2400.0)
    n_refits = 0 if session is None else int(math.ceil(session.t_ns[-1] * 1e-9 / every))
    total = sum(len(s) for _, _, s in jobs) + (n_refits if core else 0)
    points: dict[str, list[dict]] = {}
    refits: list[dict] = []
    t0 = time.perf_counter()
    with (
        threadpool_limits(limits=1),
        tqdm(total=total, file=sys.stderr, desc="pareto", unit="point") as bar,
    ):
        for group, scene, specs in jobs:
            points.setdefault(group, []).extend(pareto_bench.run_scene(scene, specs, core, bar))
        if session is not None:
            refits = pareto_bench.refit_session(session, every, core, bar)
    wall = time.perf_counter() - t0
    groups = {g: pareto_bench.aggregate(p, g) for g, p in points.items()}
    rat = {g: pareto_bench.ratios(rows) for g, rows in groups.items()}
    rr = pareto_bench.refit_ratio(refits)
    note = (
        f"Setting: {'--quick' if args.quick else 'full'}; seed {args.seed}; one process, BLAS "
        "limited to 1 thread (threadpoolctl). 2D rows average the paper's shapes "
        f"({'circle' if args.quick else 'square, circle, cross'}; n ~ 590). Times in seconds: "
        "merge+fit, field (dense grid or narrow band), mesh (marching cubes / squares). Chamfer "
        "and e against the true surface (mm): 'near data' counts only surface inside the contacts' "
        "bounding box + 0.5 m (far from all data the mean reverts to the prior mean 0 = the "
        "surface level, and every method draws phantom surface there); Q over the planted "
        "false contacts; Pareto: not dominated in (total s, Chamfer near data). 'default' is "
        "SurfaceModel with default settings: its own mesh() (grid spacing max(0.05 m, l/5) over "
        "the contacts' box + 0.5 m, narrow band, std at the vertices). sklearn GPR: "
        "C x RBF + White, one L-BFGS start, mean predicted in chunks on the same grid. "
        "Skipped: methods whose module is missing."
    )
    meta = {"note": note}
    text = pareto_bench.render(groups, rat, rr, meta) + f"\nWall time {wall:.0f} s.\n"
    (out / "pareto.md").write_text(text)
    if groups:
        pareto_bench.plot_pareto(groups, out / "pareto.png")
    if refits:
        pareto_bench.plot_refits(refits, rr.get("covered_n_raw"), out / "refit_vs_session.png")
    payload = {
        "quick": bool(args.quick),
        "seed": args.seed,
        "wall_s": wall,
        "speed_core": core is not None,
        "groups": groups,
        "points": points,
        "ratios": rat,
        "refits": refits,
        "refit_ratio": rr,
        "session_covered_s": None if session is None else session.covered_s,
    }
    (out / "results.json").write_text(
        json.dumps(payload, indent=1, allow_nan=False, default=pareto_bench.json_default)
    )
    print(text)
    print(f"wrote {out}/pareto.md, pareto.png, refit_vs_session.png, results.json")
    return 0


# ------------------------------ bench stability


def add_stability_arguments(parser: argparse.ArgumentParser) -> None:
    """Command-line options of ``groundstation bench stability``."""
    parser.add_argument("--out", default="results/stability", help="output folder (created)")
    parser.add_argument("--seeds", type=int, default=None, help="seeds per value (5; 2 --quick)")
    parser.add_argument(
        "--sweeps", default=",".join(stability_bench.SWEEPS), help="comma-separated subset"
    )
    parser.add_argument(
        "--methods", default=",".join(stability_bench.METHODS), help="comma-separated subset"
    )
    parser.add_argument("--quick", action="store_true", help="2 seeds, 2-3 values, 0.05 m grid")
    parser.add_argument("--jobs", type=int, default=2, help="worker processes (1 BLAS thread each)")


def run_stability(args: argparse.Namespace) -> int:
    """Run the sweeps, write stability.md, stability.png and results.json."""
    sweeps = [x.strip() for x in args.sweeps.split(",") if x.strip()]
    methods = [x.strip() for x in args.methods.split(",") if x.strip()]
    for sw in sweeps:
        if sw not in stability_bench.SWEEPS:
            raise ConfigError(
                f"unknown sweep {sw!r}", hint=f"choose from {', '.join(stability_bench.SWEEPS)}"
            )
    for m in methods:
        if m not in stability_bench.METHODS:
            raise ConfigError(
                f"unknown method {m!r}", hint=f"choose from {', '.join(stability_bench.METHODS)}"
            )
    seeds = args.seeds if args.seeds is not None else (2 if args.quick else 5)
    if seeds < 1 or args.jobs < 1:
        raise ConfigError(f"--seeds ({seeds}) and --jobs ({args.jobs}) must be >= 1")
    s = stability_bench.StabilitySettings(spacing=0.05 if args.quick else 0.02)
    values = {sw: stability_bench.SWEEPS[sw][1 if args.quick else 0] for sw in sweeps}
    tasks = [
        (m, sw, v, seed)
        for sw in sweeps
        for m in methods
        for v in values[sw]
        for seed in range(seeds)
    ]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    runs = stability_bench.run_all(tasks, s, args.jobs)
    wall = time.perf_counter() - t0
    summary = stability_bench.summarize(runs, values)
    setting = "--quick" if args.quick else "full"
    text = (
        stability_bench.render(summary, seeds, s, setting)
        + f"\nWall time {wall:.0f} s, --jobs {args.jobs}.\n"
    )
    (out / "stability.md").write_text(text)
    stability_bench.plot(runs, values, out / "stability.png")
    payload = {
        "settings": dataclasses.asdict(s),
        "seeds": seeds,
        "values": values,
        "chamfer_fail": stability_bench.CHAMFER_FAIL,
        "q_fail": stability_bench.Q_FAIL,
        "wall_s": wall,
        "summary": summary,
        "runs": runs,
    }
    (out / "results.json").write_text(json.dumps(payload, indent=1, allow_nan=False))
    print(text)
    print(f"wrote {out / 'stability.md'}, {out / 'stability.png'}, {out / 'results.json'}")
    return 0


# ------------------------------ bench sessions


def add_sessions_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--logs", nargs="*", default=None, help="recordings (default: suite)")
    parser.add_argument(
        "--quick", action="store_true", help="only the three bundled replay_logs/ sessions"
    )
    parser.add_argument(
        "--variant",
        action="append",
        default=[],
        metavar="NAME[:KEY=V,...]",
        help="a setting variant to compare (repeatable; default: 'default' with no overrides)",
    )
    parser.add_argument(
        "--set", action="append", default=[], metavar="KEY=VALUE", help="applies to all variants"
    )
    parser.add_argument("--cache", default="results/sessions/logs", help="generated sessions")
    parser.add_argument("--out", default="results/sessions", help="summary.md and summary.json")
    parser.add_argument("--jobs", type=int, default=2, help="sessions replayed in parallel")


def run_sessions(args: argparse.Namespace) -> int:
    from groundstation.config import load_config

    variants = [sessions_bench.Variant.parse(v) for v in args.variant] or [
        sessions_bench.Variant("default")
    ]
    if len({v.name for v in variants}) != len(variants):
        raise ConfigError("--variant names must be unique")
    for v in variants:
        load_config(None, [*args.set, *v.overrides])  # fail before any work
    if args.logs:
        logs = [str(Path(p)) for p in args.logs]
        missing = [p for p in logs if not Path(p).is_file()]
        if missing:
            raise InputDataError(f"recordings not found: {', '.join(missing)}")
    else:
        logs = [
            str(sessions_bench.ROOT / "replay_logs" / f"{n}.mcap") for n in sessions_bench.BUNDLED
        ]
        if not args.quick:
            for spec in sessions_bench.SUITE:
                print(f"bench sessions: session {spec.name}", file=sys.stderr, flush=True)
                logs.append(str(sessions_bench.generate(spec, Path(args.cache))))
    jobs = max(1, int(args.jobs))
    results: dict[str, dict] = {}
    for v in variants:
        overrides = [*args.set, *v.overrides]
        print(f"bench sessions: variant {v.name} on {len(logs)} sessions", file=sys.stderr)
        with ProcessPoolExecutor(jobs) as ex:
            reports = list(ex.map(sessions_bench.evaluate_log, logs, [overrides] * len(logs)))
        results[v.name] = {
            "overrides": overrides,
            "pooled": sessions_bench.pool(reports),
            "sessions": {
                Path(lg).stem: {
                    k: r.get(k)
                    for k in (
                        "chamfer_m",
                        "chamfer_full_m",
                        "shape_error_m",
                        "events_false",
                        "events_flagged",
                        "events_flagged_false",
                        "fp_precision",
                        "fp_recall",
                        "detection_recall",
                        "refits",
                        "refit_s_median",
                        "contacts",
                        "observations",
                    )
                }
                for lg, r in zip(logs, reports, strict=True)
            },  # fmt: skip
        }
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    text = sessions_bench.summary_markdown(results)
    (out / "summary.md").write_text(text)
    from groundstation.pipeline.outputs import _clean

    (out / "summary.json").write_text(json.dumps(_clean(results), indent=1) + "\n")
    print(text)
    print(f"bench sessions: wrote {out / 'summary.md'} and summary.json", file=sys.stderr)
    return 0


# ------------------------------ bench speed


def add_speed_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", default="results/speed", help="output folder (created)")
    parser.add_argument("--quick", action="store_true", help="no exact 3D fit, n ~ 750 in 3D")
    parser.add_argument("--chunk-mb", type=float, default=64.0, help="prediction chunk budget")


def run_speed(args: argparse.Namespace) -> int:
    import scipy.linalg  # noqa: F401  (load scipy's BLAS before limiting it)
    from threadpoolctl import threadpool_limits

    with threadpool_limits(1):
        rows = speed_bench.measure(args.quick, args.chunk_mb)
    text = "# bench speed (one process, one BLAS thread)\n\n" + speed_bench.table(rows)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "speed.md").write_text(text)
    (out / "speed.json").write_text(json.dumps(rows, indent=1) + "\n")
    print(text)
    return 0


# ------------------------------ bench fuzz


def add_fuzz_arguments(parser: argparse.ArgumentParser) -> None:
    """Command-line options of ``groundstation bench fuzz``."""
    from groundstation.bench import fuzz

    parser.add_argument(
        "--target",
        action="append",
        default=None,
        metavar="NAME",
        help=f"parser to fuzz, repeatable or comma-separated ({', '.join(fuzz.TARGETS)}; "
        "default: all)",
    )
    parser.add_argument(
        "--inputs",
        type=int,
        default=None,
        metavar="N",
        help="inputs per target (default 1,000,000; ulog 5,000: pyulog is slow and stalls)",
    )
    parser.add_argument("--seed", type=int, default=0, help="input i = f(seed, target, i)")
    parser.add_argument("--out", default="results/fuzz", help="results and reproducers folder")
    parser.add_argument(
        "--hang-s",
        type=float,
        default=None,
        help=f"an input running longer is a hang (default {fuzz.HANG_S:g} s)",
    )


def run_fuzz(args: argparse.Namespace) -> int:
    """Fuzz each target in a watched child; print the table; 1 if anything was found."""
    from groundstation.bench import fuzz

    names = [n.strip() for t in (args.target or [",".join(fuzz.TARGETS)]) for n in t.split(",")]
    names = [n for n in names if n]
    for n in names:
        if n not in fuzz.TARGETS:
            raise ConfigError(
                f"unknown fuzz target {n!r}", hint=f"one of {', '.join(fuzz.TARGETS)}"
            )
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results = []
    for n in names:
        inputs = args.inputs if args.inputs is not None else fuzz.TARGETS[n].default_inputs
        print(f"fuzz {n}: {inputs:,} inputs ...", file=sys.stderr, flush=True)
        r = fuzz.run_target(
            n, inputs, seed=args.seed, out=out, hang_s=args.hang_s,
            progress=lambda m: print(m, file=sys.stderr, flush=True),
        )  # fmt: skip
        results.append(r)
        fuzz.write_results(results, out, args.seed)
    print(fuzz.table(results))
    print(f"results: {out / 'fuzz.md'}, {out / 'fuzz.json'}", file=sys.stderr)
    return 0 if all(r.clean for r in results) else 1
