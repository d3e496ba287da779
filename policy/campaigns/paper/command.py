"""What `tools/paper.py` does with its options: the scenarios and Table I for each controller,
their JSON, figures and block under runs/paper/, and with --write-docs the docs' block and
figures. `Options` holds the command line's values, one field per option."""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rich.console import Console

from policy.campaigns.evaluation import (
    EpisodeResult,
    RunConfig,
    evaluate,
    load_controller,
    random_episodes,
)
from policy.campaigns.paper.figures import FIGURE_CONTROLLERS, plot_scenario
from policy.campaigns.paper.markdown import markdown
from policy.campaigns.paper.settings import (
    COMMITTED,
    FIGURES,
    RESULTS_MD,
    Settings,
    recorded_settings,
    write_generated,
)
from policy.campaigns.paper.table import run_table, summary, table_path
from policy.campaigns.stats import DEFAULT_RESAMPLES
from policy.tasks.scenarios import SCENARIOS
from reach_driver.controllers import Controller
from reach_driver.errors import ExtraNotInstalledError
from reach_sim_bridge.model.sensors import SensorNoise

ROOT = Path(__file__).resolve().parents[3]


@dataclass(frozen=True)
class Options:
    """The command line of `tools/paper.py` (its help says what each one does); every
    default is the committed table's setting."""

    controllers: Sequence[str] = COMMITTED.controllers
    seed: int = COMMITTED.seed
    n: int = COMMITTED.n
    seconds: float = COMMITTED.seconds
    rate: float = COMMITTED.rate_hz
    noise: bool = True
    noise_std: Sequence[float] = COMMITTED.noise or ()
    perturb: float = COMMITTED.perturb
    more_seeds: Sequence[int] = COMMITTED.more_seeds
    skip_table: bool = False
    skip_scenarios: bool = False
    runs: Path = field(default_factory=lambda: ROOT / "runs" / "paper")
    docs: Path = field(default_factory=lambda: ROOT / "docs")
    write_docs: bool = False
    force: bool = False
    reuse: bool = False
    resamples: int = DEFAULT_RESAMPLES
    ci_seed: int = 0


def settings_from(args: Options) -> Settings:
    return Settings(
        controllers=tuple(args.controllers),
        seed=args.seed,
        n=args.n,
        seconds=float(args.seconds),
        rate_hz=float(args.rate),
        noise=(float(args.noise_std[0]), float(args.noise_std[1])) if args.noise else None,
        perturb=float(args.perturb),
        more_seeds=tuple(args.more_seeds) if not args.skip_table else (),
        table=not args.skip_table,
        scenarios=not args.skip_scenarios,
    )


def execute(args: Options) -> int:
    """Run the scenarios and the table, write the results (and the docs when asked); the
    exit code (2: a bad option or a refused --write-docs, 1: no controller could be run)."""
    console = Console()
    settings = settings_from(args)
    if args.skip_table and args.skip_scenarios:
        console.print("[red]error:[/red] --skip-table and --skip-scenarios leave nothing to run")
        return 2
    if args.resamples < 1:
        console.print("[red]error:[/red] --resamples must be at least 1")
        return 2
    doc = args.docs / RESULTS_MD
    if args.write_docs:
        reference = recorded_settings(doc) or COMMITTED
        diffs = settings.differences(reference)
        if (args.resamples, args.ci_seed) != (DEFAULT_RESAMPLES, 0):
            diffs.append(
                f"bootstrap: {args.resamples} resamples, seed {args.ci_seed} here, "
                f"{DEFAULT_RESAMPLES} and 0 in the committed text"
            )
        if diffs and not args.force:
            console.print(
                f"[red]refusing to write {doc}[/red]: this run's settings differ from those "
                "of the table there:\n  "
                + "\n  ".join(diffs)
                + "\nRun without --write-docs (results go to "
                f"{args.runs}/), or add --force to replace the committed table."
            )
            return 2
    try:
        noise = SensorNoise(*settings.noise) if settings.noise else None
        table_config = RunConfig(
            seconds=settings.seconds,
            rate_hz=settings.rate_hz,
            noise=noise,
            seed=settings.seed,
            param_spread=settings.perturb,
        )
        scenario_config = RunConfig(seconds=settings.seconds, rate_hz=settings.rate_hz)
        episodes = random_episodes(settings.n, settings.seed)
    except ValueError as exc:
        console.print(f"[red]error:[/red] {exc}")
        return 2
    figures = args.docs / FIGURES if args.write_docs else args.runs / FIGURES
    args.runs.mkdir(parents=True, exist_ok=True)
    t_start = time.monotonic()

    scenarios: dict[str, list[EpisodeResult]] = {}
    table: dict[str, dict[str, Any]] = {}
    skipped: dict[str, str] = {}
    reused: list[str] = []
    ran: list[str] = []
    for name in settings.controllers:
        try:
            controller: Controller = load_controller(name)
        except (ValueError, OSError, RuntimeError, ExtraNotInstalledError) as exc:
            console.print(f"[yellow]{name}: skipped[/yellow] ({exc})")
            skipped[name] = str(exc)
            continue
        ran.append(name)
        if settings.scenarios:
            console.print(f"[bold]{name}[/bold]: scenarios")
            scen = [sc.episode() for sc in SCENARIOS]
            ev = evaluate(controller, scen, scenario_config, name=name)
            scenarios[name] = ev.results
            (args.runs / f"scenarios_{name}.json").write_text(json.dumps(ev.to_dict(), indent=1))
        if settings.table:
            console.print(f"[bold]{name}[/bold]: {settings.n} random targets, seed {settings.seed}")
            path = table_path(args.runs, name, settings.seed, settings.seed)
            table[name] = run_table(name, episodes, table_config, path, args.reuse, console, reused)
            s = summary(table[name])
            console.print("  " + ", ".join(f"{k} {v:.4g}" for k, v in s.items()))
    if not ran:
        console.print("[red]no controller could be run[/red]")
        return 1
    more: dict[int, dict[str, dict[str, Any]]] = {}
    for seed in settings.more_seeds:
        config = dataclasses.replace(table_config, seed=seed)
        eps = random_episodes(settings.n, seed)
        for name in ran:
            console.print(f"[bold]{name}[/bold]: {settings.n} random targets, seed {seed}")
            path = table_path(args.runs, name, seed, settings.seed)
            more.setdefault(seed, {})[name] = run_table(
                name, eps, config, path, args.reuse, console, reused
            )

    figure_links: dict[int, str] = {}
    link_base = args.docs if args.write_docs else args.runs
    for sc in SCENARIOS if scenarios else ():
        shown = {n: scenarios[n][sc.number - 1] for n in FIGURE_CONTROLLERS if n in scenarios}
        if not shown:
            shown = {n: r[sc.number - 1] for n, r in scenarios.items()}
        path = figures / f"scenario{sc.number}.png"
        plot_scenario(shown, sc, path, scenario_config)
        try:
            figure_links[sc.number] = path.resolve().relative_to(link_base.resolve()).as_posix()
        except ValueError:
            figure_links[sc.number] = path.resolve().as_posix()

    block, numbers = markdown(
        settings,
        scenarios,
        table,
        more,
        table_config,
        scenario_config,
        figure_links,
        skipped,
        args.resamples,
        args.ci_seed,
        reused,
    )
    (args.runs / "paired_differences.json").write_text(json.dumps(numbers, indent=1))
    preview = args.runs / "results_block.md"
    preview.write_text(block + "\n", encoding="utf-8")
    wrote = [f"{args.runs}/*.json", str(preview), f"{figures}/*.png"]
    if args.write_docs:
        write_generated(doc, block)
        wrote.insert(0, str(doc))
        text = doc.read_text(encoding="utf-8")
        stale = sorted(p.name for p in figures.glob("*.png") if f"{FIGURES}/{p.name}" not in text)
        if stale:
            console.print(
                f"[yellow]not referenced by {doc} (delete them):[/yellow] {', '.join(stale)}"
            )
    console.print(f"wrote {', '.join(wrote)} in {time.monotonic() - t_start:.0f} s")
    return 0


def build_parser() -> argparse.ArgumentParser:
    c = COMMITTED
    p = argparse.ArgumentParser(
        prog="paper.py",
        description="Run the paper's four scenarios and its random-target comparison "
        "(Table I) for each controller, with bootstrap confidence intervals. Every default "
        "is the setting of the table committed in docs/results.md. By default only "
        "runs/paper/ is written (JSON, a preview of the generated block, figures); "
        "--write-docs also writes docs/figures/*.png and the generated block of "
        "docs/results.md. Controllers that cannot be loaded (e.g. ddpg-distilled without its "
        "weights) are skipped and listed.",
    )
    p.add_argument(
        "--controllers",
        nargs="+",
        default=list(c.controllers),
        help=f"entry-point names (default: {' '.join(c.controllers)})",
    )
    p.add_argument("--seed", type=int, default=c.seed, help=f"seed of Table I ({c.seed})")
    p.add_argument("--n", type=int, default=c.n, help=f"random targets per seed ({c.n})")
    p.add_argument(
        "--seconds", type=float, default=c.seconds, help=f"episode length, s ({c.seconds:g})"
    )
    p.add_argument(
        "--rate", type=float, default=c.rate_hz, help=f"control rate, Hz ({c.rate_hz:g})"
    )
    assert c.noise is not None
    p.add_argument(
        "--noise",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="sensor noise in the comparison (default: on; scenarios are always noise-free)",
    )
    p.add_argument(
        "--noise-std",
        nargs=2,
        type=float,
        default=list(c.noise),
        metavar=("RAD", "RAD_S"),
        help=f"sensor noise sigma on position and velocity ({c.noise[0]} {c.noise[1]})",
    )
    p.add_argument(
        "--perturb",
        type=float,
        default=c.perturb,
        metavar="SPREAD",
        help=f"arm parameters degraded by U(1 +- SPREAD) in the comparison ({c.perturb:g}; "
        "0 = nominal)",
    )
    p.add_argument(
        "--more-seeds",
        nargs="*",
        type=int,
        default=list(c.more_seeds),
        metavar="SEED",
        help="repeat the comparison on these seeds too and pool them in the paired "
        f"differences (default: {' '.join(map(str, c.more_seeds))}; none: --more-seeds)",
    )
    p.add_argument("--skip-table", action="store_true", help="only the four scenarios")
    p.add_argument("--skip-scenarios", action="store_true", help="only the comparison")
    p.add_argument(
        "--runs",
        type=Path,
        default=ROOT / "runs" / "paper",
        help="JSON, block preview and (without --write-docs) figures (the repository's runs/paper)",
    )
    p.add_argument(
        "--docs",
        type=Path,
        default=ROOT / "docs",
        help="docs folder: --write-docs writes DOCS/results.md's block and DOCS/figures "
        "(the repository's docs/)",
    )
    p.add_argument(
        "--write-docs",
        action="store_true",
        help="write DOCS/figures/*.png and replace the generated block of DOCS/results.md; "
        "refused when the settings differ from the table there, unless --force",
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="with --write-docs: replace a table made with other settings",
    )
    p.add_argument(
        "--reuse",
        action="store_true",
        help="reload a table run from RUNS/*.json when it is the same controller on the same "
        "episodes and settings, instead of running it again (scenarios always run)",
    )
    p.add_argument(
        "--resamples",
        type=int,
        default=DEFAULT_RESAMPLES,
        help=f"bootstrap resamples ({DEFAULT_RESAMPLES})",
    )
    p.add_argument("--ci-seed", type=int, default=0, help="bootstrap seed (0)")
    return p


def main(argv: list[str] | None = None) -> int:
    """`tools/paper.py`'s command line: parse `argv` and run it."""
    return execute(Options(**vars(build_parser().parse_args(argv))))
