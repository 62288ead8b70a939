"""The toolkit's exceptions: every user-facing failure is one of these, with a message naming the file or key."""

import logging
import sys
from collections.abc import Callable


class CosimError(Exception):
    """Base class: the CLI prints these as one line instead of a traceback."""


class ConfigError(CosimError):
    """A config file or override is missing, malformed, or names an unknown key / bad value."""


class SeedError(ConfigError, ValueError):
    """A seed that is no episode seed (`cosim.config.check_seed`); a ValueError as well, as an API's caller
    passing a bad argument expects."""


class NetError(CosimError):
    """A net file or net description is missing, malformed, or inconsistent with the net."""


class SimulationError(CosimError):
    """SUMO failed to start, crashed, or a second simulation was requested in one process."""


class EpisodeError(SimulationError):
    """An episode that fails the same way again on a fresh worker (the same seed and actions): a fault of the
    config or the net (SUMO refusing an input, say), not bad luck; a run stops at once, its folder as it was."""


def check_at_least(name: str, value: float | None, least: float) -> None:
    """`ConfigError` naming `name` (a key or a flag) unless `value` is None or >= `least`."""
    if value is not None and value < least:
        raise ConfigError(f"{name}: must be >= {least}, got {value}")


def run_script(main: Callable[[], object], log: logging.Logger) -> None:
    """Run a script's `main`: bad input (a CosimError) is one logged line and exit status 2, as from the cosim
    command, not a traceback."""
    try:
        main()
    except CosimError as exc:
        log.error("%s", exc)
        sys.exit(2)
