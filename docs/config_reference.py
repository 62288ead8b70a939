"""The config key reference, in Markdown, from `cosim.config.Config.model_json_schema()`.

`docs/conf.py` puts it into `configs.md` (where the page has `<!-- config-reference -->`) at every build, so the
page cannot go stale; `python docs/config_reference.py` prints it. Each section is one table: key, type,
built-in default (what a key that no config file gives gets), bounds, description (its `[unit]` ends it).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
MARKER = "<!-- config-reference -->"


def _type(prop: dict[str, Any]) -> str:
    if "anyOf" in prop:
        return " or ".join(_type(p) for p in prop["anyOf"])
    if "enum" in prop:
        return " | ".join(f"`{json.dumps(v)}`" for v in prop["enum"])
    kind = prop.get("type", "any")
    if kind == "array":
        if "prefixItems" in prop:
            return "[" + ", ".join(_type(p) for p in prop["prefixItems"]) + "]"
        return f"list of {_type(prop.get('items', {}))}"
    if kind == "object":
        values = prop.get("additionalProperties")
        return f"mapping to {_type(values)}" if isinstance(values, dict) else "mapping"
    return {"number": "number", "integer": "integer", "string": "string", "boolean": "boolean",
            "null": "null"}.get(kind, kind)


def _number(value: float) -> str:
    return f"{value:g}" if isinstance(value, float) else str(value)


def _bounds(prop: dict[str, Any]) -> str:
    """The schema's bounds of a value (or of each item of a list or tuple), e.g. `> 0, <= 1`."""
    out = []
    for key, sign in (("exclusiveMinimum", ">"), ("minimum", ">="), ("exclusiveMaximum", "<"), ("maximum", "<=")):
        if key in prop:
            out.append(f"{sign} {_number(prop[key])}")
    if not out:
        for inner in (prop.get("items"), *(prop.get("prefixItems") or ()), *(prop.get("anyOf") or ())):
            if isinstance(inner, dict) and (bounds := _bounds(inner)):
                return bounds + (" each" if "items" in prop or "prefixItems" in prop else "")
    return ", ".join(out)


def _show(value: Any) -> str:
    if isinstance(value, str) and value.startswith(str(ROOT)):  # the default net, as a path in the repository
        value = Path(value).relative_to(ROOT).as_posix()
    text = json.dumps(value, ensure_ascii=False)
    return "`" + text.replace("|", "\\|") + "`"


def _cell(text: str) -> str:
    """A table cell: no line breaks, `|` escaped, `<` outside code spans written as an entity."""
    parts = " ".join(text.split()).replace("|", "\\|").split("`")
    return "`".join(p if i % 2 else p.replace("<", "&lt;") for i, p in enumerate(parts))


def _first_line(doc: str | None) -> str:
    return " ".join((doc or "").strip().split("\n\n")[0].split())


def _table(path: str, cls: Any, defs: dict[str, Any]) -> list[str]:
    """The key table of the section model `cls` at the dotted `path`, then one for each section nested in it."""
    # A section given in a file starts from its class's defaults (for `merger:` not Config's, noted below).
    section_defaults = cls().model_dump(mode="json")
    lines = [f"### `{path}:`", ""]
    if doc := _first_line(cls.__doc__):
        lines += [_cell(doc), ""]
    lines += ["| key | type | default | bounds | description |", "|---|---|---|---|---|"]
    nested = []
    for key, prop in defs[cls.__name__]["properties"].items():
        if "$ref" in prop:  # a section inside the section: its own table
            nested.append(key)
            lines.append(f"| `{path}.{key}` | section | see `{path}.{key}:` | | {_cell(prop.get('description', ''))} |")
            continue
        lines.append(f"| `{path}.{key}` | {_cell(_type(prop))} | {_show(section_defaults.get(key))} | "
                     f"{_bounds(prop)} | {_cell(prop.get('description', ''))} |")
    lines.append("")
    for key in nested:
        lines += _table(f"{path}.{key}", cls.model_fields[key].annotation, defs)
    return lines


def markdown() -> str:
    from cosim.config import Config, DriverConfig, load_config

    schema = Config.model_json_schema()
    defs = schema["$defs"]
    defaults = Config().model_dump(mode="json")
    default_yaml = load_config(ROOT / "configs" / "default.yaml").model_dump(mode="json")
    lines: list[str] = []
    for section, ref in schema["properties"].items():
        if "$ref" not in ref:
            continue  # `source`: where a config came from, not a key
        cls = Config.model_fields[section].annotation
        section_defaults = cls().model_dump(mode="json")
        lines += _table(section, cls, defs)
        if cls is DriverConfig and defaults[section] != section_defaults:
            changed = ", ".join(f"`{section}.{k}` {_show(v)}" for k, v in defaults[section].items()
                                if section_defaults.get(k) != v)
            lines += [f"Without a `{section}:` section the built-in config gives {changed}; a `{section}:` section "
                      "in a file starts from the defaults in the table.", ""]
        differs = {f"{section}.{k}": v for k, v in _flat(default_yaml[section]).items()
                   if _flat(defaults[section]).get(k) != v}
        if differs:
            given = ", ".join(f"`{k}` {_show(v)}" for k, v in differs.items())
            lines += [f"`configs/default.yaml` gives {given}.", ""]
    return "\n".join(lines)


def _flat(section: dict[str, Any]) -> dict[str, Any]:
    """A section's values by dotted key below it, nested sections' keys included (`weights.merge`)."""
    out: dict[str, Any] = {}
    for key, value in section.items():
        if isinstance(value, dict) and key != "lc_params":  # lc_params: a mapping value, not a section
            out.update({f"{key}.{k}": v for k, v in _flat(value).items()})
        else:
            out[key] = value
    return out


if __name__ == "__main__":
    print(markdown())
