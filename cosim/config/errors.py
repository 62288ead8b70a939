"""How a config problem is worded: one line per problem, naming the dotted key, what is allowed and where the
value came from.

Contract: a section's validator raises `_problem(message, key)` (a pydantic error of type `cosim`, `key` the
field it blames below that section); `_error(exc, root, where, source, overrides)` turns pydantic's
`ValidationError` into one `ConfigError`, one line per problem: the dotted key (`scenario.n_avs`, `train.lr`)
and what is allowed (the bounds, the choices, or for an unknown key the section's keys), prefixed by `_origin`
with where the value came from: the `--set KEY=VALUE` that gave it (an override given as a string; one given in
a dict is code's, named by its key alone), else the file when loaded from one. `yaml_problem` puts PyYAML's
message on one line. This module knows no section: it is the bottom of `cosim.config`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from types import MappingProxyType
from typing import Any

import yaml
from pydantic import BaseModel, ValidationError
from pydantic_core import PydanticCustomError

from cosim.errors import ConfigError


def _problem(message: str, key: str = "") -> PydanticCustomError:
    """A problem worded for `ConfigError`; `key`: the field a section's validator blames, below that section."""
    return PydanticCustomError("cosim", "{message}", {"message": message, "key": key})



def yaml_problem(exc: yaml.YAMLError, lines: bool = True) -> str:
    """PyYAML's message on one line (its own spans several, with a caret under the spot): where, what, and
    what it was reading."""
    if not isinstance(exc, yaml.MarkedYAMLError) or exc.problem_mark is None:
        return " ".join(str(exc).split())

    def at(mark: Any) -> str:
        return f"line {mark.line + 1}, column {mark.column + 1}" if lines else f"column {mark.column + 1}"

    text = f"{at(exc.problem_mark)}: {exc.problem}"
    if exc.context:
        text += f" ({exc.context}" + (f" from {at(exc.context_mark)})" if exc.context_mark else ")")
    return text



# How a problem's message words what pydantic's error type asks for.
_EXPECTED = {
    "int_type": "an integer", "int_parsing": "an integer", "int_from_float": "an integer",
    "float_type": "a number", "float_parsing": "a number", "finite_number": "a finite number",
    "bool_type": "true or false", "bool_parsing": "true or false", "string_type": "a string",
    "tuple_type": "a list", "list_type": "a list", "dict_type": "a mapping", "mapping_type": "a mapping",
    "model_type": "a mapping", "model_attributes_type": "a mapping",
}
_BOUNDS = {"greater_than": (">", "gt"), "greater_than_equal": (">=", "ge"),
           "less_than": ("<", "lt"), "less_than_equal": ("<=", "le")}


def _error(exc: ValidationError, root: type[BaseModel], where: str, source: str | None = None,
           overrides: Mapping[str, str] = MappingProxyType({})) -> ConfigError:
    """One line per problem, naming the dotted key below `where` and where its value came from (`_origin`)."""
    lines = []
    for err in exc.errors(include_url=False):
        loc, kind, ctx = list(err["loc"]), err["type"], err.get("ctx") or {}
        value = err.get("input")
        got, prefix = _show(value), ""
        if kind == "cosim":
            if ctx.get("key"):
                loc.append(ctx["key"])
            text = ctx["message"]
        elif kind == "extra_forbidden":
            allowed = _keys_at(root, loc[:-1])
            prefix, text = "config key ", "unknown key" + (f"; allowed: {', '.join(allowed)}" if allowed else "")
        elif isinstance(value, float) and not math.isfinite(value):  # pydantic checks bounds first
            text = f"expected a finite number, got {got}"
        elif kind in _BOUNDS:
            op, bound = _BOUNDS[kind]
            text = f"must be {op} {_number(ctx[bound])}, got {got}"
        elif kind == "literal_error":
            text = f"expected {ctx['expected']}, got {got}"
        elif kind in _EXPECTED:
            text = f"expected {_EXPECTED[kind]}, got {got}"
        else:
            text = f"{err['msg']}, got {got}"
        key = _dotted(where, loc)
        lines.append(_origin(key, f"{prefix}{key or 'config'}: {text}", text, source, overrides))
    return ConfigError("\n".join(dict.fromkeys(lines)))


def _origin(key: str, line: str, text: str, source: str | None, overrides: Mapping[str, str]) -> str:
    """The problem `line` (`text` about `key`) prefixed with where the value came from: the `--set` that gave the
    key (its problem alone follows: `--set sim.horizon=-1: must be > 0, got -1`) or a section above it; nothing
    for a value set in code; else the file `source`, with the `--set`s inside a section whose own rule is broken
    (the values judged together came from both)."""
    owner = next((k for k in overrides if key == k or key.startswith((f"{k}.", f"{k}["))), None)
    if owner is not None:
        label = overrides[owner]
        return line if not label else f"{label}: {text}" if key == owner else f"{label}: {line}"
    inside = [label for k, label in overrides.items() if label and key and k.startswith(f"{key}.")]
    origin = " with ".join(filter(None, [source, ", ".join(inside)]))
    return f"{origin}: {line}" if origin else line


def _dotted(where: str, loc: Sequence[str | int]) -> str:
    path = where
    for part in loc:
        path += f"[{part}]" if isinstance(part, int) else f"{'.' if path else ''}{part}"
    return path


def _keys_at(root: type[BaseModel], loc: Sequence[str | int]) -> list[str]:
    """The keys of the section at `loc` below `root` (none where `loc` leads to no section model)."""
    model: Any = root
    for part in loc:
        field = model.model_fields.get(part) if isinstance(part, str) else None
        model = field.annotation if field is not None else None
        if not (isinstance(model, type) and issubclass(model, BaseModel)):
            return []
    return [k for k in model.model_fields if k != "source"]


def _number(bound: Any) -> str:
    # A bound on a float field comes back as a float: "> 0", not "> 0.0".
    return f"{bound:g}" if isinstance(bound, float) else str(bound)


def _show(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."
