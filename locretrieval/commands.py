"""The ``locretrieval`` command (also ``python -m locretrieval``)::

    locretrieval evaluate [KEY=VALUE | GROUP=OPTION ...]   # benchmark a descriptor on a scene
    locretrieval train [...]                               # train a descriptor for localization
    locretrieval export [...]                              # pairs files, descriptors, ONNX
    locretrieval report RUN [RUN ...] [--output DIR]       # the report of finished runs again

``evaluate``, ``train`` and ``export`` are Hydra applications on the configs the package ships
(`configs_dir`): overrides as ``key=value`` and ``group=option``, ``-m`` for a sweep, ``--cfg job``
to print the config; ``--config-dir DIR`` adds a folder of one's own configs to Hydra's search
path (``DIR/model/mine.yaml`` is ``model=mine``; ``--config-name mine`` a primary config of one's
own there). Their outputs go under the current folder (``outputs/``, ``multirun/``; the cache
``.cache/``: ``paths``). Each command's ``--help`` is written here (`command_help`), like
Lightning's CLI: what it does, examples, its config groups with their options, the options.
The scripts at the repository's root (evaluate.py, train.py, export.py, report.py) call `main`.
"""

from __future__ import annotations

import argparse
import contextlib
import difflib
import logging
import shutil
import sys
import tempfile
import textwrap
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from omegaconf import DictConfig

import locretrieval  # registers the config resolvers; imports zlib before pycolmap
from locretrieval.cli import check_command_line, reported_mistakes
from locretrieval.console import console_output, one_console
from locretrieval.resources import configs_dir

#: Columns of the help texts.
HELP_WIDTH = 100


def evaluate_task(cfg: DictConfig) -> None:
    """``locretrieval evaluate``: the benchmark of ``cfg`` into Hydra's output folder."""
    from hydra.core.hydra_config import HydraConfig

    with console_output(), reported_mistakes():  # a mistake of the user's: its message, no traceback
        from locretrieval.build import build_evaluation  # here, so that `--help` imports none of the heavy modules
        from locretrieval.evaluation import evaluate

        evaluate(build_evaluation(cfg), Path(HydraConfig.get().runtime.output_dir))


def train_task(cfg: DictConfig) -> float | None:
    """``locretrieval train``; returns the ``optimized_metric`` (the objective of ``hparams_search=localization``)."""
    with console_output(), reported_mistakes():
        from locretrieval.build import build_training
        from locretrieval.cli import composed_training_scenes
        from locretrieval.training.run import optimized_value, train

        run = build_training(cfg, composed_training_scenes(cfg))  # every key, part and file checked first
        one_console()  # `import lightning` gave the lightning logger a console of its own
        return optimized_value(run.objective, train(run, Path(cfg.output_dir)))


def export_task(cfg: DictConfig) -> None:
    """``locretrieval export``: the formats of ``cfg.export`` into Hydra's output folder."""
    from hydra.core.hydra_config import HydraConfig

    with console_output(), reported_mistakes():
        from locretrieval.build import build_export
        from locretrieval.export.run import export

        export(build_export(cfg), Path(HydraConfig.get().runtime.output_dir))


@dataclass(frozen=True)
class Command:
    """A subcommand: its one-line ``summary``, ``examples`` (arguments, what they do) and, for a
    Hydra application, its ``task`` (its config is ``<name>.yaml`` of `configs_dir`)."""

    summary: str
    examples: tuple[tuple[str, str], ...]
    task: Callable[[DictConfig], Any] | None = None


COMMANDS = {
    "evaluate": Command(
        "benchmark a global descriptor and the ground-truth rankings on a scene, by localization",
        (
            ("", "DenseVLAD on the built-in synthetic scene"),
            ("data.render.environment=street", "the synthetic street"),
            ("data=kapture data.mapping=/d/mapping data.queries=[/d/query]", "a kapture dataset of your own"),
            ("model=precomputed model.path=/d/global_features/AP-GeM", "descriptors computed elsewhere"),
            ("-m model=netvlad,apgem paths.data_dir=/data", "a sweep: one run per model"),
            ("data=baidu dry_run=true", "the SfM work and its time forecast, nothing run or written"),
        ),
        evaluate_task,
    ),
    "train": Command(
        "train a descriptor for localization, supervised by ground-truth relevance",
        (
            ("", "EfficientNet-Lite0 + GeM on the synthetic scene, loss=listwise"),
            ("debug=quick", "under a minute: for trying a change"),
            ("loss=triplet train_relevance=frustum trainer.max_epochs=20", "another loss and relevance"),
            ("-m loss=ap,triplet,contrastive,listwise", "a sweep, one folder per run, summary.md"),
            ("-m hparams_search=localization hydra/launcher=joblib_local", "an Optuna study, trials in parallel"),
            ("ckpt_path=<run>/checkpoints/last.ckpt", "resume"),
        ),
        train_task,
    ),
    "export": Command(
        "export rankings, descriptors and networks in the formats hloc, kapture and COLMAP read",
        (
            ("", "DenseVLAD on the synthetic scene: pairs files and descriptors"),
            ("data=baidu model=precomputed model.feature_name=AP-GeM-LM18", "a published dataset's"),
            ("'export=[onnx]' model=checkpoint model.weights=<run>/checkpoints/last.ckpt", "a network as ONNX"),
        ),
        export_task,
    ),
    "report": Command(
        "regenerate the report of evaluation runs, or the summary of training runs and sweeps",
        (
            ("outputs/evaluate/synthetic/densevlad/<date>", "one run's report again"),
            ("multirun/evaluate/<date> --output reports/all-models", "one report over a multirun"),
            ("RUN --gallery queries=all k=10 --images data/", "galleries from the dataset's images"),
            ("multirun/train/localization", "a train sweep: summary.md, .csv, .html"),
        ),
    ),
}


def main(argv: Sequence[str] | None = None) -> None:
    """``locretrieval <command> [arguments]`` (``argv``: the arguments, default ``sys.argv[1:]``)."""
    arguments = list(sys.argv[1:] if argv is None else argv)
    if not arguments or arguments[0] in ("-h", "--help"):
        print(overview())
        raise SystemExit(0 if arguments else 2)
    if arguments[0] == "--version":
        print(f"locretrieval {locretrieval.__version__}")
        return
    name, rest = arguments[0], arguments[1:]
    if name not in COMMANDS:
        near = difflib.get_close_matches(name, list(COMMANDS), n=1)
        suggestion = f"; did you mean {near[0]}?" if near else ""
        sys.stderr.write(f"locretrieval: unknown command {name!r}{suggestion} (commands: {', '.join(COMMANDS)})\n")
        raise SystemExit(2)
    locretrieval.exit_without_final_collection()
    if COMMANDS[name].task is None:
        report_command(rest)
    else:
        hydra_command(name, rest)


def overview() -> str:
    """``locretrieval --help``: the commands and where to read more."""
    width = max(map(len, COMMANDS)) + 2
    return "\n".join(
        [
            "usage: locretrieval <command> [arguments]",
            "",
            "Image retrieval for visual localization: benchmark global descriptors by localization accuracy and",
            "train them for it (Humenberger et al., IJCV 2022).",
            "",
            "commands:",
            *(f"  {name:<{width}}{command.summary}" for name, command in COMMANDS.items()),
            "",
            "options:",
            f"  {'-h, --help':<{width + 2}}this text; `locretrieval <command> --help`: a command's",
            f"  {'--version':<{width + 2}}the installed version",
            "",
            "Outputs go under the current folder: outputs/, multirun/ and the cache .cache/.",
        ]
    )


def hydra_command(name: str, arguments: list[str]) -> None:
    """The Hydra application ``name`` on the shipped configs with the command line ``arguments``:
    its help (`command_help`), the overrides Hydra would refuse or misreport (`check_command_line`),
    then Hydra's run; a dry run (`dry_run_folder`) keeps no run folder."""
    if "-h" in arguments or "--help" in arguments:
        print(command_help(name))
        return
    check_command_line(configs_dir(), name, arguments)
    import hydra

    command_line, task = list(sys.argv), COMMANDS[name].task

    def task_of_this_command_line(cfg: DictConfig) -> Any:
        sys.argv = command_line  # what a relaunched process runs again (Lightning's DDP ranks): this command
        return task(cfg)

    task_of_this_command_line.__module__ = task.__module__  # Hydra names the job after it
    with dry_run_folder(arguments) as extra:
        sys.argv = [f"locretrieval {name}", *arguments, *extra]  # what Hydra parses
        hydra.main(version_base="1.3", config_path=str(configs_dir()), config_name=name)(task_of_this_command_line)()


@contextlib.contextmanager
def dry_run_folder(arguments: Sequence[str]) -> Iterator[list[str]]:
    """Hydra's overrides that keep a dry run (``dry_run=true`` on the command line of a single run)
    from writing a run folder: its log and Hydra's files go to a temporary folder, deleted after.
    Nothing for any other command line."""
    from hydra._internal.utils import get_args_parser  # what @hydra.main parses the command line with
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    parsed = get_args_parser().parse_args(list(arguments))
    try:
        overrides = OverridesParser.create().parse_overrides(parsed.overrides)
    except HydraException:  # a syntax error: Hydra's message says where
        overrides = []
    dry = any(o.key_or_group == "dry_run" and not o.is_sweep_override() and o.value() is True for o in overrides)
    if parsed.multirun or not dry:
        yield []
        return
    folder = tempfile.mkdtemp(prefix="locretrieval-dry-run-")
    try:
        yield [f"hydra.run.dir='{folder}'", "hydra.output_subdir=null"]
    finally:
        logging.shutdown()  # the run's log file is closed before its folder goes
        shutil.rmtree(folder, ignore_errors=True)


def command_help(name: str) -> str:
    """``locretrieval <name> --help``: usage, what it does, examples, its config groups (each
    with the option the config chooses and the others the shipped configs hold) and options."""
    command = COMMANDS[name]
    lines = [
        f"usage: locretrieval {name} [KEY=VALUE | GROUP=OPTION ...] [-m] [--cfg job] [--config-dir DIR]",
        "",
        f"{command.summary[0].upper()}{command.summary[1:]}.",
        "",
        "examples:",
        *example_lines(name, command),
        "",
        "config groups (GROUP=OPTION; the config's choice in brackets, then the others):",
    ]
    choices = group_choices(name)
    width = max(map(len, choices), default=0) + 2
    for group, chosen in choices.items():
        others = [option for option in group_options(group) if option != chosen]
        text = f"[{chosen or 'null'}] {' '.join(others)}".rstrip()
        lines += textwrap.wrap(
            text, HELP_WIDTH, initial_indent=f"  {group:<{width}}", subsequent_indent=" " * (width + 2)
        )
    lines += [
        "",
        "options:",
        "  -m, --multirun         one run per combination of comma-separated values (a sweep)",
        "  --cfg job              print the composed config instead of running (--package model: one section)",
        "  --config-dir DIR       add a folder of your own configs to Hydra's search path (DIR/model/mine.yaml:",
        "                         model=mine); --config-name NAME: a primary config of your own there",
        "  --hydra-help           Hydra's own options",
        "",
        "Every key of the config is set as KEY=VALUE (seed=1, retrieval.depth=20; + adds a key, ~ removes one).",
        "Outputs go under the current folder: outputs/, multirun/ and the cache .cache/ (paths.root_dir).",
    ]
    return "\n".join(lines)


def example_lines(name: str, command: Command) -> list[str]:
    """A command's examples, each followed by what it does."""
    lines = []
    for arguments, what in command.examples:
        lines += [f"  locretrieval {name} {arguments}".rstrip(), f"      {what}"]
    return lines


def group_choices(name: str) -> dict[str, str | None]:
    """The config groups of the config ``name`` (Hydra's ``hydra.runtime.choices``: nested ones
    such as ``model/backbone`` too; not Hydra's own nor a group placed twice with ``@``) and the
    option each takes (``None``: none chosen)."""
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(configs_dir()), version_base="1.3"):
        choices = compose(name, return_hydra_config=True).hydra.runtime.choices
    return {
        str(group): None if option is None else str(option)
        for group, option in sorted(choices.items())
        if not str(group).startswith("hydra/") and "@" not in str(group)
    }


def group_options(group: str) -> list[str]:
    """The options the shipped configs hold for ``group`` (its folder's YAML files)."""
    return sorted(path.stem for path in (configs_dir() / group).glob("*.yaml"))


REPORT_DESCRIPTION = """\
Regenerate the report of one or several finished evaluation runs from their tables, or the
summary of train runs and sweeps.

A directory without results.csv is searched for runs below it (a Hydra multirun). Only files
inside the runs given are read, their YAML as written (no interpolation resolved), and only the
output folder is written: the galleries' images must lie inside a run or below an --images folder
(a shared run's images.csv may list any file), thumbnails are cached only under --thumbnail-cache.
"""


def report_parser() -> argparse.ArgumentParser:
    """The arguments of ``locretrieval report``."""
    examples = "examples:\n" + "\n".join(example_lines("report", COMMANDS["report"]))
    parser = argparse.ArgumentParser(
        prog="locretrieval report",
        description=REPORT_DESCRIPTION,
        epilog=examples,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("runs", nargs="+", type=Path, help="run directories, or folders holding them")
    parser.add_argument("--output", type=Path, help="report directory (default: the single run directory given)")
    parser.add_argument("--groundtruth", help="ground truth of the correlation analysis (default: relative pose)")
    parser.add_argument(
        "--formats", nargs="*", default=["png", "pdf"], help="figure formats (default: png pdf; none given: no figures)"
    )
    parser.add_argument(
        "--gallery",
        nargs="+",
        default=[],
        metavar="KEY=VALUE",
        help="report.gallery settings replacing the first run's (e.g. queries=all k=10)",
    )
    parser.add_argument(
        "--images",
        nargs="+",
        default=[],
        type=Path,
        metavar="DIR",
        help="folders whose images the galleries may read besides the runs' own (e.g. the dataset's folder)",
    )
    parser.add_argument("--thumbnail-cache", type=Path, help="folder caching the galleries' thumbnails (default: none)")
    return parser


def report_command(arguments: Sequence[str]) -> None:
    """``locretrieval report``: its arguments parsed, then `report` (a mistake: one screen)."""
    parser = report_parser()
    args = parser.parse_args(list(arguments))
    logging.basicConfig(level=logging.INFO, format="[%(levelname)s] %(name)s: %(message)s")
    logging.getLogger("alembic").setLevel(logging.WARNING)  # Optuna's storage imports it, which logs each plugin
    if args.output is None:
        if len(args.runs) != 1:
            parser.error("--output is required when several runs are given")
        args.output = args.runs[0]
    with console_output(), reported_mistakes():  # a folder that is not a run, a damaged table: its message
        report(args)


def report(args: argparse.Namespace) -> None:
    """The summary of train runs and sweeps, or the report of evaluation runs (`REPORT_DESCRIPTION`)."""
    from locretrieval.build import build_report_gallery
    from locretrieval.config import ConfigError
    from locretrieval.report import build_report
    from locretrieval.report.run_files import load_yaml, run_file
    from locretrieval.report.tables import find_run_dirs
    from locretrieval.report.training_summary import MULTIRUN_FILE, is_training_folder, write_summary

    for path in args.runs:  # its YAML within limits.yaml_nodes before the summary reads it
        if run_file(path, MULTIRUN_FILE).is_file():
            load_yaml(path / MULTIRUN_FILE)
    training = [is_training_folder(path) for path in args.runs]
    if any(training):
        if not all(training):
            raise ConfigError("give either train runs and sweeps or evaluation runs, not both")
        print(write_summary(args.runs, args.output))
        return
    gallery = build_report_gallery(find_run_dirs(args.runs)[0], args.gallery)
    print(
        build_report(
            args.runs,
            args.output,
            args.groundtruth,
            args.formats,
            gallery=gallery,
            thumbnail_cache=args.thumbnail_cache,
            image_roots=args.images,
        )
    )
