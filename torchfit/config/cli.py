"""Command-line plumbing shared by the tools: --config, --data, --out, --set, exit codes.

Exit codes (README "Exit codes"): :data:`EXIT_OK` 0, every subject fitted (``ok`` or
``poor_fit``: a poor fit is a result, to be checked in its overlays); :data:`EXIT_FAILED` 1,
some subject failed (its reason in summary.csv); :data:`EXIT_CONFIG` 2, a bad config, argument
or template; :data:`EXIT_OUTPUT` 3, the run folder cannot be written; :data:`EXIT_INPUT` 4, the
dataset itself is missing or unreadable.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
from pathlib import Path

from torchfit.config.loader import load_config
from torchfit.config.schema import Config
from torchfit.errors import ConfigError, DataError, OutputError, TorchfitError

__all__ = [
    "add_config_args",
    "add_executor_args",
    "config_from_args",
    "run_folder",
    "exit_code",
    "EXIT_OK",
    "EXIT_FAILED",
    "EXIT_CONFIG",
    "EXIT_OUTPUT",
    "EXIT_INPUT",
]

EXIT_OK = 0
EXIT_FAILED = 1
EXIT_CONFIG = 2
EXIT_OUTPUT = 3
EXIT_INPUT = 4


def exit_code(error: TorchfitError) -> int:
    """The exit code of a run stopped by ``error``: 3 for an OutputError, 4 for a DataError
    (the dataset), 2 otherwise (config, arguments, template)."""
    if isinstance(error, OutputError):
        return EXIT_OUTPUT
    if isinstance(error, DataError):
        return EXIT_INPUT
    return EXIT_CONFIG


def add_config_args(parser: argparse.ArgumentParser) -> None:
    """Add ``--config``, ``--data``, ``--out``, ``--set`` and ``--verbose``."""
    parser.add_argument("--config", type=Path, help="YAML config file (see configs/)")
    parser.add_argument(
        "--data", type=Path, help="dataset folder or manifest (overrides data.root)"
    )
    parser.add_argument("--out", type=Path, help="run folder (overrides run.out)")
    parser.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a config value, e.g. --set solver.max_iter=50 (repeatable)",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")


def add_executor_args(parser: argparse.ArgumentParser) -> None:
    """Add ``--executor``, ``--address`` and ``--workers`` (``run.executor``, ``run.address``,
    ``run.workers``)."""
    parser.add_argument(
        "--executor",
        choices=("local", "ray"),
        help="local (default): this process; ray: batches of subjects as Ray tasks",
    )
    parser.add_argument(
        "--address",
        help="Ray cluster to join: auto, HOST:PORT or ray://HOST:PORT "
        "(default: start a local cluster)",
    )
    parser.add_argument(
        "--workers", type=int, help="fits at once (Ray tasks; default: CPUs / run.num_threads)"
    )


def config_from_args(args: argparse.Namespace, schema: type = Config):
    """Load the config named by ``args`` with ``--set`` overrides, then --data (made absolute
    from the current directory), --out and, where the parser has them, --executor, --address
    and --workers."""
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(levelname)s %(name)s: %(message)s",
    )
    config = load_config(args.config, list(args.overrides), schema)
    if args.data is not None:
        data = dataclasses.replace(config.data, root=str(args.data.absolute()))
        config = dataclasses.replace(config, data=data)
    if args.out is not None:
        run = dataclasses.replace(config.run, out=str(args.out))
        config = dataclasses.replace(config, run=run)
    changes = {
        key: getattr(args, key)
        for key in ("executor", "address", "workers")
        if getattr(args, key, None) is not None
    }
    if changes:
        if changes.get("workers", 1) < 1:
            raise ConfigError(f"--workers: expected an integer >= 1, got {changes['workers']}")
        config = dataclasses.replace(config, run=dataclasses.replace(config.run, **changes))
    return config


def run_folder(config: Config, base: Path = Path("runs")) -> Path:
    """The run folder: ``run.out`` or ``runs/<run.name>``."""
    return Path(config.run.out) if config.run.out else base / config.run.name
