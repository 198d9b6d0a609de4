"""Command-line plumbing shared by the tools: --config, --data, --out, --set."""

from __future__ import annotations

import argparse
import dataclasses
import logging
from pathlib import Path

from torchfit.config.loader import load_config
from torchfit.config.schema import Config

__all__ = ["add_config_args", "config_from_args", "run_folder"]


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


def config_from_args(args: argparse.Namespace, schema: type = Config):
    """Load the config named by ``args`` with ``--set`` overrides, then --data / --out."""
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(levelname)s %(name)s: %(message)s",
    )
    config = load_config(args.config, list(args.overrides), schema)
    if args.data is not None:
        data = dataclasses.replace(config.data, root=str(args.data))
        config = dataclasses.replace(config, data=data)
    if args.out is not None:
        run = dataclasses.replace(config.run, out=str(args.out))
        config = dataclasses.replace(config, run=run)
    return config


def run_folder(config: Config, base: Path = Path("runs")) -> Path:
    """The run folder: ``run.out`` or ``runs/<run.name>``."""
    return Path(config.run.out) if config.run.out else base / config.run.name
