"""The `cosim` command: one subcommand per job, each living in the module that owns the job.

Contract: every subcommand module exposes `add_arguments(parser)` and `run(args) -> int`. Modules are
imported only when their subcommand runs, so `cosim build-net` never loads torch. A `CosimError`
(bad config, bad net, SUMO failure) or an OS error (a folder that cannot be written, a file where a folder
should be) is printed as one line, exit status 2, not a traceback. Ctrl-C (SIGINT) and SIGTERM stop a
command cleanly (a training run writes its checkpoint first) with exit status 130.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import signal
import sys
import time
from collections.abc import Sequence

from tqdm.contrib.logging import logging_redirect_tqdm

from cosim.errors import CosimError

# subcommand -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "build-net": ("sumo_net.build", "build an on-ramp merge network with netconvert"),
    "run-scenario": ("cosim.run_scenario", "run the env with a scripted or random policy"),
    "bench": ("cosim.bench", "measure env speed against a bare libsumo loop"),
    "train": ("agents.train", "train AV policies with multi-agent A2C or PPO"),
    "sweep": ("agents.sweep", "train and evaluate every (SVO angle, seed) within a budget, report against baselines"),
    "evaluate": ("cosim.evaluation.runner", "evaluate trained AVs or a baseline policy"),
    "compare": ("cosim.evaluation.compare", "compare evaluated runs: tables, plots, Markdown report"),
}


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = argparse.ArgumentParser(prog="cosim", description=__doc__.splitlines()[0])
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (_, help_text) in COMMANDS.items():
        sub.add_parser(name, help=help_text, add_help=False)
    # Parse up to the command name first, so that only the chosen command's module is imported.
    at = next((i for i, a in enumerate(argv) if a in COMMANDS), len(argv))
    head = parser.parse_args(argv[: at + 1])
    module = importlib.import_module(COMMANDS[head.command][0])
    full = argparse.ArgumentParser(prog=f"cosim {head.command}", description=COMMANDS[head.command][1])
    full.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    module.add_arguments(full)
    args = full.parse_args(argv[at + 1:])
    logging.basicConfig(level=logging.DEBUG if args.verbose or head.verbose else logging.INFO,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s", datefmt="%H:%M:%S")
    log = logging.getLogger("cosim")
    previous = signal.signal(signal.SIGTERM, _terminate)  # a scheduler's stop is handled like Ctrl-C
    try:
        with logging_redirect_tqdm():  # log lines above progress bars, not through them
            return int(module.run(args) or 0)
    except CosimError as exc:
        log.error("%s", exc)
        return 2
    except OSError as exc:
        where = f" {exc.filename}" if exc.filename else ""
        log.error("cosim %s:%s: %s", head.command, where, exc.strerror or exc)
        return 2
    except KeyboardInterrupt:
        log.warning("cosim %s: interrupted", head.command)
        return 130
    finally:
        signal.signal(signal.SIGTERM, previous)


def _terminate(signum: int, frame: object) -> None:
    raise KeyboardInterrupt


class Heartbeat:
    """True once every `every_s` seconds (the first call included): when a command without a terminal (no
    progress bar) logs a line."""

    def __init__(self, every_s: float) -> None:
        self.every_s = every_s
        self.last = -float("inf")

    def __call__(self) -> bool:
        now = time.monotonic()
        if now - self.last >= self.every_s:
            self.last = now
            return True
        return False


def add_config_arguments(parser: argparse.ArgumentParser, default: str | None = "configs/default.yaml") -> None:
    """The config options every env-using command shares."""
    parser.add_argument("--config", default=default, help="experiment YAML (default: %(default)s)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="override a config key, e.g. --set reward.phi=0.785 (repeatable); a path given here "
                             "(net.file) is relative to the working directory, one in a YAML file to that file")


if __name__ == "__main__":
    raise SystemExit(main())
