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
import time
from collections.abc import Sequence
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
        "--engines", default="simple,mujoco", help="SITL physics engines (simple,mujoco)"
    )
    parser.add_argument(
        "--seeds", default="100-103", help="seeds reported (never used for tuning), e.g. 100-103"
    )
    parser.add_argument(
        "--train-seeds", default="0-3", help="seeds the evidence model is fitted on (--train)"
    )
    parser.add_argument(
        "--train",
        action="store_true",
        help="fit the evidence model on --train-seeds first, write it to --out and report with it",
    )
    parser.add_argument(
        "--degree",
        type=int,
        choices=(1, 2),
        default=1,
        help="with --train: 1 fits the shipped, linear model; 2 adds every product of two "
        "inputs (better on the SITL's tuning seeds, extrapolates badly: see the README)",
    )
    parser.add_argument(
        "--variant",
        action="append",
        default=[],
        metavar="NAME[:KEY=VALUE,...]",
        help="detector variants compared on the same flights (default: impulse, "
        "threshold-1.2G, threshold-0.6G)",
    )
    parser.add_argument(
        "--paths",
        help=f"aggressive_flight paths, or 'none' (default {','.join(detector_bench.REAL_PATHS)})",
    )
    parser.add_argument(
        "--files", help=f"IMU files per path (default {','.join(detector_bench.REAL_FILES)})"
    )
    parser.add_argument("--cache", default=None, help="flight cache (default OUT/flights)")
    parser.add_argument("--jobs", type=int, default=2, help="worker processes")
    parser.add_argument("--quick", action="store_true", help="one scene per seed, no free flights")
    parser.add_argument("--config", help="TOML config (the base of every variant)")


def _csv_list(text: str | None, default: Sequence[str]) -> list[str]:
    return [v.strip() for v in (text.split(",") if text else default) if v.strip()]


def _burst_context(
    events: Sequence, engines: Sequence[str], config: str | None, overrides: Sequence[str]
) -> dict:
    """The burst-context table of one detector variant, with the window and line its own
    settings use (``contact.burst_window_s``, ``contact.reject_p_false``)."""
    from groundstation.config import load_config

    c = load_config(config, list(overrides)).contact
    return {
        "burst_window_s": c.burst_window_s,
        "burst_line": c.reject_p_false,
        "burst_context": detector_bench.burst_context_by_engine(
            events, engines, c.burst_window_s, c.reject_p_false
        ),
    }


def run_detector(args: argparse.Namespace) -> int:
    """Generate the flights, (fit the evidence model), run every variant, write the tables."""
    db = detector_bench
    engines = _csv_list(args.engines, db.ENGINES)
    unknown = sorted(set(engines) - set(db.ENGINES))
    if unknown:
        raise db.BenchDataError(f"unknown engines {unknown}; use {','.join(db.ENGINES)}")
    seeds = db.parse_seeds(args.seeds)
    train_seeds = db.parse_seeds(args.train_seeds)
    if args.train and set(seeds) & set(train_seeds):
        raise db.BenchDataError(
            f"--seeds and --train-seeds overlap in {sorted(set(seeds) & set(train_seeds))}",
            hint="report on seeds that were not used to fit the model",
        )
    variants = [db.Variant.parse(v) for v in args.variant] or list(db.DEFAULT_VARIANTS)
    paths = _csv_list(args.paths, db.REAL_PATHS)
    paths = [] if paths == ["none"] else paths
    files = _csv_list(args.files, db.REAL_FILES)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    cache = Path(args.cache) if args.cache else out / "flights"
    model_note = "bundled evidence model"
    if args.train:
        specs = db.flight_suite(engines, train_seeds, args.quick)
        runs = db.run_flights(specs, cache, [db.Variant("train")], args.config, args.jobs)
        events, _ = runs["train"]
        provenance = (
            f"groundstation bench detector --train: engines {','.join(engines)}, train seeds "
            f"{args.train_seeds}, {len(specs)} flights, "
            f"{sum(e.kind == 'touch' for e in events)} touches, "
            f"{sum(e.kind == 'slow_touch' for e in events)} slow touches, "
            f"{sum(e.kind == 'gust' for e in events)} gusts, "
            f"{sum(e.kind == 'none' for e in events)} unmatched candidates "
            f"(weighted to {db.UNMATCHED_SHARE:.0%} of the false class); "
            f"{db.EVIDENCE_FITS[args.degree].describe()}"
        )
        model = db.fit_evidence_model(events, provenance, db.EVIDENCE_FITS[args.degree])
        model_path = out / "evidence_model.json"
        db.write_json(model_path, model.to_dict())
        model_note = f"model fitted on train seeds {args.train_seeds}: {model_path}"
        variants = [
            db.Variant(v.name, (f"contact.evidence_model={model_path}", *v.overrides))
            for v in variants
        ]
        print(f"wrote {model_path} ({provenance})", file=sys.stderr)
    specs = db.flight_suite(engines, seeds, args.quick)
    labelled = db.run_flights(specs, cache, variants, args.config, args.jobs)
    real = db.run_real(paths, files, cache, variants, args.config, args.jobs)
    if paths:
        print(db.ATTRIBUTION, file=sys.stderr)
    results = {
        "command": "groundstation bench detector " + " ".join(sys.argv[3:]),
        "seeds": seeds,
        "train_seeds": train_seeds if args.train else None,
        "evidence_model": model_note,
        "flights": [s.name for s in specs],
        "variants": {
            v.name: {
                "overrides": list(v.overrides),
                "engines": db.by_engine(*labelled[v.name], engines),
                "real": real.get(v.name),
                **_burst_context(labelled[v.name][0], engines, args.config, v.overrides),
            }
            for v in variants
        },
        "attribution": db.ATTRIBUTION,
    }
    md = "\n".join([
        "# Contact detector on both physics engines and real flights",
        f"Command: `{results['command'].strip()}`  ",
        f"Reported seeds {args.seeds}; {model_note}; {len(specs)} simulated flights.",
        "",
        db.markdown(results),
        f"Attribution: {db.ATTRIBUTION}",
    ])  # fmt: skip
    (out / "detector.md").write_text(md + "\n")
    db.write_json(out / "results.json", results)
    for v in variants:
        db.events_csv(out / f"events_{v.name}.csv", labelled[v.name][0])
    print(md)
    print(f"wrote {out / 'detector.md'}, {out / 'results.json'}")
    return 0


# ------------------------------ bench pareto

PARETO_SCENES = ("paper3d", "session40")


def add_pareto_arguments(parser: argparse.ArgumentParser) -> None:
    """Command-line options of ``groundstation bench pareto``."""
    parser.add_argument("--out", default="results/pareto", help="output folder (created)")
    parser.add_argument(
        "--quick",
        action="store_true",
        help="CI size: n ~ 700 in the 3D set, coarse exact grid, 5-min session",
    )
    parser.add_argument(
        "--scenes",
        default=",".join(PARETO_SCENES),
        help=f"comma-separated subset of {', '.join(PARETO_SCENES)}",
    )
    parser.add_argument(
        "--methods",
        default=",".join(pareto_bench.METHODS),
        help=f"comma-separated subset of {', '.join(pareto_bench.METHODS)} (3D set)",
    )
    parser.add_argument(
        "--refit-every",
        type=float,
        default=None,
        help="session refit interval, s (30; 60 with --quick)",
    )
    parser.add_argument("--seed", type=int, default=0, help="data seed")


def run_pareto(args: argparse.Namespace) -> int:
    """Run every method, print the tables, write the charts, pareto.md and results.json."""
    from threadpoolctl import threadpool_limits
    from tqdm import tqdm

    scenes = _csv_list(args.scenes, PARETO_SCENES)
    methods = _csv_list(args.methods, pareto_bench.METHODS)
    for sc in scenes:
        if sc not in PARETO_SCENES:
            raise ConfigError(
                f"unknown scene {sc!r}", hint=f"choose from {', '.join(PARETO_SCENES)}"
            )
    for m in methods:
        if m not in pareto_bench.METHODS:
            raise ConfigError(
                f"unknown method {m!r}", hint=f"choose from {', '.join(pareto_bench.METHODS)}"
            )
    every = args.refit_every if args.refit_every is not None else (60.0 if args.quick else 30.0)
    if not every > 0:
        raise ConfigError(f"--refit-every must be > 0 s, got {every}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    import scipy.linalg  # noqa: F401  (load every BLAS before limiting it)

    data = session = None
    if "paper3d" in scenes:
        kw = dict(n_contacts=300, n_external=150) if args.quick else {}
        data = scenes3d.paper3d(args.seed, **kw)
    if "session40" in scenes:
        session = scenes3d.session40(args.seed, duration_s=300.0 if args.quick else 2400.0)
    n_points = 0 if data is None else pareto_bench.count_points(methods)
    n_refits = 0 if session is None else 2 * int(math.ceil(session.t_ns[-1] * 1e-9 / every))
    spacing = 0.08 if args.quick else 0.04
    rows: list[dict] = []
    refits: list[dict] = []
    t0 = time.perf_counter()
    with (
        threadpool_limits(limits=1),
        tqdm(total=n_points + n_refits, file=sys.stderr, desc="pareto", unit="fit") as bar,
    ):
        if data is not None:
            rows = pareto_bench.run_paper3d(data, tuple(methods), spacing, bar)
        if session is not None:
            refits = pareto_bench.refit_session(session, every, bar)
    wall = time.perf_counter() - t0
    summary = pareto_bench.refit_summary(refits)
    note = (
        f"Setting: {'--quick' if args.quick else 'full'}; seed {args.seed}; one process, BLAS "
        f"limited to one thread (threadpoolctl); wall time {wall:.0f} s. 3D set: "
        f"{'' if data is None else len(data.y)} rows, its clean control without the false "
        f"contacts. Exact methods on a dense {spacing} m grid over the scene; mappers mesh their "
        f"own region. Session: a refit every {every:g} s of the growing stream (warm, as live). "
        "Metrics: module docstring of groundstation/bench/pareto.py."
    )
    text = pareto_bench.render(rows, summary, note)
    (out / "pareto.md").write_text(text)
    if rows:
        pareto_bench.plot_pareto(rows, out / "pareto.png")
    if refits:
        pareto_bench.plot_refits(refits, session.covered_s, out / "refit_vs_session.png")
    payload = {
        "quick": bool(args.quick),
        "seed": args.seed,
        "wall_s": wall,
        "refit_every_s": every,
        "paper3d": rows,
        "refits": refits,
        "refit_summary": summary,
        "session_covered_s": None if session is None else session.covered_s,
    }
    (out / "results.json").write_text(
        json.dumps(payload, indent=1, allow_nan=False, default=pareto_bench.json_default)
    )
    print(text)
    print(f"wrote {out}/pareto.md, results.json and the charts")
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
    parser.add_argument("--config", default=None, help="TOML configuration (base of every variant)")
    parser.add_argument("--cache", default="results/sessions/logs", help="generated flights")
    parser.add_argument(
        "--out", default="results/sessions", help="summary.md/.json/.png and tasks/ (one per task)"
    )
    parser.add_argument(
        "--jobs", type=int, default=None, help="local Dask workers (default: cores)"
    )
    parser.add_argument(
        "--engines", default="simple,mujoco", help="SITL physics engines of the generated flights"
    )
    parser.add_argument(
        "--seeds", default="100-102", help="seeds of the generated flights, e.g. 100-102"
    )
    parser.add_argument(
        "--scheduler",
        default=None,
        metavar="ADDRESS",
        help="existing Dask scheduler, e.g. tcp://10.0.0.5:8786 (default: a local cluster)",
    )
    parser.add_argument(
        "--map",
        choices=("live", "final"),
        default="final",
        help="replay --map of every task (default final: the bench judges the final map)",
    )
    parser.add_argument("--quiet", action="store_true", help="no progress bars")


def run_sessions(args: argparse.Namespace) -> int:
    """Build the flight list, generate missing flights and run everything through batch."""
    from groundstation.config import load_config
    from groundstation.pipeline.batch import Variant, plan_batch
    from groundstation.pipeline.batch_outputs import write_summary
    from groundstation.pipeline.pooling import summarize, summary_markdown
    from groundstation.runtime.batch import Cluster, execute, log_input, run_all, software_id
    from groundstation.runtime.configuration import recorded_note, recording_resolver

    variants = [Variant.parse(v) for v in args.variant]
    engines = [e.strip() for e in args.engines.split(",") if e.strip()]
    bad = [e for e in engines if e not in detector_bench.ENGINES]
    if bad or not engines:
        raise ConfigError(
            f"--engines {args.engines!r}: use {' and/or '.join(detector_bench.ENGINES)}"
        )
    seeds = detector_bench.parse_seeds(args.seeds)
    for v in variants or [Variant("default")]:
        load_config(args.config, [*args.set, *v.overrides])  # a bad setting fails before any work
    cache = Path(args.cache).resolve()  # workers of a remote cluster may run elsewhere
    out = Path(args.out)
    with Cluster(args.scheduler, args.jobs) as cluster:
        logs = []
        if args.logs:
            paths = [Path(p) for p in args.logs]
            missing = [str(p) for p in paths if not p.is_file()]
            if missing:
                raise InputDataError(f"recordings not found: {', '.join(missing)}")
            logs = [log_input(p, role="log") for p in paths]
        else:
            vehicle = detector_bench.VEHICLE[sessions_bench.BUNDLED_ENGINE]
            for n in sessions_bench.BUNDLED:
                path = sessions_bench.ROOT / "replay_logs" / f"{n}.mcap"
                logs.append(log_input(path, vehicle, engine="simple", role="bundled", pair=n))
            flights = [] if args.quick else sessions_bench.flights(engines, seeds)
            todo = [f for f in flights if not (cache / f"{f.spec.name}.mcap").is_file()]
            if todo:
                print(
                    f"bench sessions: generating {len(todo)} flights on {cluster.description}",
                    file=sys.stderr,
                )
            made = run_all(
                cluster, detector_bench.generate, [(f.spec, cache) for f in todo], "flights",
                args.quiet,
            )  # fmt: skip
            for f, (_, err) in zip(todo, made, strict=True):
                if err:
                    print(f"bench sessions: flight {f.spec.name} FAILED: {err}", file=sys.stderr)
            for f in flights:
                path = cache / f"{f.spec.name}.mcap"
                if path.is_file():
                    logs.append(
                        log_input(path, detector_bench.VEHICLE[f.spec.engine],
                                  engine=f.spec.engine, role=f.role, pair=f.pair)
                    )  # fmt: skip
        plan = plan_batch(
            logs, variants, recording_resolver(args.config),
            base_overrides=args.set, map_mode=args.map, software=software_id(),
        )  # fmt: skip
        on_top = "--config/--set on top"
        if not args.logs:
            on_top = f"the bench's airframe (bench.detector.VEHICLE) and {on_top}"
        for line in recorded_note([log.recorded for log in logs], "bench sessions", on_top):
            print(line, file=sys.stderr)
        print(
            f"bench sessions: {len(logs)} logs x {len(plan.variants)} variants = "
            f"{len(plan.tasks)} tasks on {cluster.description}",
            file=sys.stderr,
        )
        run = execute(plan, out / "tasks", cluster, snapshots=1, quiet=args.quiet)
    summary = summarize(plan, run.records)
    comparison = sessions_bench.compare(plan, run.records)
    summary["groups"] = comparison
    summary["batch"] = {
        "ran": run.ran, "skipped": run.skipped, "failed": run.failed, "wall_s": run.wall_s,
        "cluster": cluster.description, "map": args.map, "engines": engines, "seeds": seeds,
    }  # fmt: skip
    overrides = {v.name: [*args.set, *v.overrides] for v in plan.variants}
    text = sessions_bench.markdown(comparison, overrides)
    text += "\n" + summary_markdown(summary, "All tasks (groundstation batch summary)")
    write_summary(summary, out, markdown=text, title="bench sessions")
    sessions_bench.control_chart(comparison, out / "control.png")
    print(text)
    print(
        f"bench sessions: {run.ran} tasks run, {run.skipped} finished earlier, {run.failed} "
        f"failed; wrote {out / 'summary.md'}, summary.json, summary.png, control.png",
        file=sys.stderr,
    )
    return 1 if run.failed else 0


# ------------------------------ bench speed


def add_speed_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", default="results/speed", help="output folder (created)")
    parser.add_argument("--quick", action="store_true", help="no exact 3D fit, n ~ 750 in 3D")
    parser.add_argument("--chunk-mb", type=float, default=64.0, help="prediction chunk budget")
    parser.add_argument(
        "--replay",
        action="append",
        default=[],
        metavar="LOG",
        help="also time replay's decode + detect path on this recording (repeatable): seconds "
        "per log-minute and times real time",
    )
    parser.add_argument(
        "--replay-only", action="store_true", help="only the --replay rows (no estimator rows)"
    )


def run_speed(args: argparse.Namespace) -> int:
    import scipy.linalg  # noqa: F401  (load scipy's BLAS before limiting it)
    from threadpoolctl import threadpool_limits

    with threadpool_limits(1):
        rows = [] if args.replay_only else speed_bench.measure(args.quick, args.chunk_mb)
        rows += speed_bench.replay_throughput(args.replay)
    text = "# bench speed (one process, one BLAS thread)\n\n" + speed_bench.table(rows)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "speed.md").write_text(text)
    (out / "speed.json").write_text(json.dumps(rows, indent=1) + "\n")
    print(text)
    return 0


# ------------------------------ bench inject


def add_inject_arguments(parser: argparse.ArgumentParser) -> None:
    db = detector_bench
    parser.add_argument("--out", default="results/inject", help="inject.md and inject.json")
    parser.add_argument("--cache", default=None, help="imported flights (default OUT/flights)")
    parser.add_argument(
        "--paths", help=f"aggressive_flight paths (default {','.join(db.REAL_PATHS)})"
    )
    parser.add_argument("--files", help=f"IMU files per path (default {','.join(db.REAL_FILES)})")
    parser.add_argument(
        "--at", type=float, default=0.5, help="where in the flight the contact is planted (0-1)"
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of the contact's direction")
    parser.add_argument("--config", default=None, help="TOML configuration")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")


def run_inject(args: argparse.Namespace) -> int:
    """Plant one false contact in each real flight, replay on the live cadence, tabulate."""
    from groundstation.bench import inject as inject_bench
    from groundstation.config import load_config

    if not 0.0 <= args.at <= 1.0:
        raise ConfigError(f"--at must be in [0, 1], got {args.at}")
    cfg = load_config(args.config, overrides=args.set)
    out = Path(args.out)
    cache = Path(args.cache) if args.cache else out / "flights"
    logs = inject_bench.real_logs(
        _csv_list(args.paths, detector_bench.REAL_PATHS),
        _csv_list(args.files, detector_bench.REAL_FILES),
        cache,
    )
    rows = []
    for log, name in logs:
        rows.append(inject_bench.measure(log, name, cfg, at=args.at, seed=args.seed))
        print(f"{name}: {rows[-1]}", file=sys.stderr)
    text = "# bench inject (one false contact planted in each real flight)\n\n"
    text += inject_bench.markdown(rows)
    out.mkdir(parents=True, exist_ok=True)
    (out / "inject.md").write_text(text)
    (out / "inject.json").write_text(json.dumps(rows, indent=1) + "\n")
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
