"""Loading a config: YAML files and their `base:` chain, `--set` overrides, one validation of the merged result.

Contract: `load_config(path_or_dict_or_Config, overrides)` returns a `Config` or raises `ConfigError` with one
line per problem (`cosim.config.errors`). A YAML file's `base:` chain (relative to the file; each file's keys
merged over its base's, so experiments state only what differs) and the overrides (`{"reward.phi": 0.785}` or
`["reward.phi=0.785"]`, values read as YAML scalars; an override replaces its key whole) are merged into one raw
dict that one `Config.model_validate` checks, so a value is judged the same wherever it came from; a later layer
that states one of a net-relative key's twins clears the others (`TWINS`). Relative paths in `net` are resolved
against the YAML file's folder (in an override or a dict: against the working directory). A file must be UTF-8
YAML with no key given twice in a mapping (`read_yaml`, for every YAML file a user may have edited); a file or
override that is not is one line naming it and the position. `parse_section` validates one section alone.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, TypeVar

import yaml

from cosim.config.errors import yaml_problem
from cosim.config.sections import Config, _clear_twins, _Section
from cosim.config.types import _resolve
from cosim.errors import ConfigError

_T = TypeVar("_T")


def parse_section(cls: type[_T], data: Any, where: str) -> _T:
    """Validate one section (a mapping; None: all defaults; an instance passes) into the model `cls`; problems
    raise `ConfigError` naming `where.key`."""
    if isinstance(data, cls):
        return data
    if not issubclass(cls, _Section):
        raise TypeError(f"parse_section: {cls!r} is not a config section model")
    return cls.model_validate({} if data is None else data, context={"where": where})



def load_config(
    config: str | Path | Mapping[str, Any] | Config | None = None,
    overrides: Mapping[str, Any] | Sequence[str] | None = None,
) -> Config:
    """Load and validate a config from a YAML path, a dict, or an existing `Config`, applying overrides."""
    source = None
    if config is None:
        data: dict[str, Any] = {}
    elif isinstance(config, Config):
        data, source = config.to_dict(), config.source
    elif isinstance(config, Mapping):
        data = _plain(config)
    else:
        path = Path(config)
        data, source = _read_yaml(path), str(path)
    parsed = _parse_overrides(overrides)
    # Where each overridden value came from, for the error lines: a string is the command line's --set, a
    # mapping's value was set in code (no input of the user's to name, and not the file's).
    given = ({key: "" for key in parsed} if isinstance(overrides, Mapping)
             else {item.partition("=")[0].strip(): f"--set {item.strip()}" for item in overrides or ()})
    for section in {key.partition(".")[0] for key in parsed}:  # overrides replace the files' twins (TWINS)
        if isinstance(data.get(section), dict):
            _clear_twins(section, data[section], {k.partition(".")[2]: v for k, v in parsed.items()
                                                  if k.partition(".")[0] == section})
    for key, value in parsed.items():
        _set_dotted(data, key, value)
    data["source"] = source
    return Config.model_validate(data, context={"source": source, "overrides": given})


def _plain(value: Any) -> Any:
    """A copy of nested mappings and sequences as dicts and lists, which overrides can then be set in."""
    if isinstance(value, Mapping):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    return value


# The keys that name a file: in a YAML file, relative to that file (scripts/snapshot_run.py writes them so).
FILE_KEYS = (("net", "file"), ("net", "description"), ("train", "init_from"))


def _read_yaml(path: Path, seen: tuple[Path, ...] = ()) -> dict[str, Any]:
    """A YAML config as a dict; `base: other.yaml` (relative to this file) is read first and this file's
    keys are merged over it, so experiments state only what differs."""
    if not path.is_file():
        raise ConfigError(f"config file {path}: not found")
    loaded = read_yaml(path)
    if loaded is not None and not isinstance(loaded, dict):
        raise ConfigError(f"config file {path}: expected a mapping of sections at top level")
    data = loaded or {}
    for section, key in FILE_KEYS:  # paths in a file are relative to that file
        part = data.get(section)
        if isinstance(part, dict) and isinstance(part.get(key), str):
            part[key] = str(_resolve(part[key], path.resolve().parent))
    base = data.pop("base", None)
    if base is None:
        return data
    base_path = (path.resolve().parent / str(base)).resolve()
    if base_path in seen:
        raise ConfigError(f"config file {path}: base {base} includes itself")
    merged = _read_yaml(base_path, (*seen, path.resolve()))
    _merge(merged, data)
    return merged


def _merge(into: dict[str, Any], over: Mapping[str, Any], section: str = "") -> None:
    for key, value in over.items():
        if isinstance(value, Mapping) and isinstance(into.get(key), dict):
            if not section:  # a later layer's twin replaces the earlier layer's (TWINS)
                _clear_twins(key, into[key], value)
            _merge(into[key], value, key)
        else:
            into[key] = value


def _parse_overrides(overrides: Mapping[str, Any] | Sequence[str] | None) -> dict[str, Any]:
    if overrides is None:
        return {}
    if isinstance(overrides, Mapping):
        return dict(overrides)
    parsed = {}
    for item in overrides:
        key, sep, raw = item.partition("=")
        if not sep or not key:
            raise ConfigError(f"override {item!r}: expected KEY=VALUE, e.g. reward.phi=0.785")
        try:
            parsed[key.strip()] = yaml.load(raw, Loader=_ConfigLoader)
        except yaml.YAMLError as exc:
            raise ConfigError(f"override {key.strip()}: {raw!r} is not a YAML value: "
                              f"{yaml_problem(exc, lines=False)}") from None
    return parsed


def read_yaml(path: Path) -> Any:
    """A YAML file's content (None for an empty one), read as config files are: UTF-8, no key given twice in a
    mapping; otherwise `ConfigError` naming the file and the position, on one line."""
    raw = path.read_bytes()
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = raw[: exc.start].count(b"\n") + 1
        raise ConfigError(f"config file {path}: not UTF-8 text (byte 0x{raw[exc.start]:02x} on line {line})") from None
    try:
        return yaml.load(text, Loader=_ConfigLoader)
    except yaml.YAMLError as exc:
        raise ConfigError(f"config file {path}: not valid YAML: {yaml_problem(exc)}") from None


class _ConfigLoader(yaml.SafeLoader):
    """PyYAML's safe loader, refusing a key given twice in one mapping: YAML requires keys to be unique, and
    PyYAML would keep the last silently, losing the first (a whole `sim:` section, say) unseen."""

    def compose_document(self) -> yaml.Node:
        node = super().compose_document()
        _check_unique_keys(node, "", set())
        return node


def _check_unique_keys(node: yaml.Node, where: str, done: set[int]) -> None:
    if id(node) in done:  # an alias: checked where its anchor is (and a recursive one would never end)
        return
    done.add(id(node))
    children: list[tuple[str, yaml.Node]] = []
    if isinstance(node, yaml.MappingNode):
        first: dict[tuple[str, Any], yaml.Node] = {}
        for key, value in node.value:
            # `<<: *base` merges a mapping whose keys this one overrides on purpose.
            if key.tag != "tag:yaml.org,2002:merge" and isinstance(key, yaml.ScalarNode):
                dotted = f"{where}.{key.value}" if where else str(key.value)
                earlier = first.setdefault((key.tag, key.value), key)
                if earlier is not key:
                    raise yaml.constructor.ConstructorError(
                        problem=f"key {dotted} given twice (first on line {earlier.start_mark.line + 1})",
                        problem_mark=key.start_mark)
                children.append((dotted, value))
            else:
                children.append((where, value))
    elif isinstance(node, yaml.SequenceNode):
        children = [(f"{where}[{i}]", item) for i, item in enumerate(node.value)]
    for dotted, child in children:
        _check_unique_keys(child, dotted, done)



def _set_dotted(data: dict[str, Any], key: str, value: Any) -> None:
    """Put an override into the raw dict. It replaces its key whole: `hv.lc_params={}` empties the mapping,
    where a `base:` file's mapping is merged into key by key."""
    node = data
    *parents, leaf = key.split(".")
    for i, part in enumerate(parents):
        child = node.setdefault(part, {})
        if not isinstance(child, dict):
            raise ConfigError(f"override {key}: {'.'.join(parents[: i + 1])} is not a section")
        node = child
    node[leaf] = value
