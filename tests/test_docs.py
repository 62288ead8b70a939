"""The README and the docs say only what the code takes: every `cosim` command they show (code blocks and inline
code) names a real subcommand, only flags that subcommand's parser has, values it accepts and config keys that
exist (`--set`); every relative link and image they give exists. No SUMO runs."""

from __future__ import annotations

import argparse
import re
import shlex
from collections.abc import Iterator
from pathlib import Path

import pytest

from cosim.cli import COMMANDS
from cosim.config import load_config
from cosim.errors import ConfigError

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
PAGES = [README, *sorted((ROOT / "docs").glob("*.md"))]

FENCE = re.compile(r"^(?P<fence>`{3,}|~{3,})(?P<info>[^\n]*)\n(?P<body>.*?)^(?P=fence)[ \t]*$", re.M | re.S)
CODE_SPAN = re.compile(r"(?<!`)`([^`]+)`(?!`)")
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
PLACEHOLDER = re.compile(r"[A-Z][A-Z0-9_]*")  # NAME, DIR, RUN: a value to fill in
WRAPPER = re.compile(r"^(?:xvfb-run(?:\s+-\S+)*\s+)")  # a command run under xvfb-run is still a cosim command


def code_texts(markdown: str) -> Iterator[str]:
    """Each line of each code block (not MyST directives such as literalinclude, whose body is options), then
    each inline code span, its line breaks read as spaces as Markdown renders them."""
    for block in FENCE.finditer(markdown):
        if not block["info"].strip().startswith("{"):
            yield from block["body"].splitlines()
    for span in CODE_SPAN.finditer(FENCE.sub("", markdown)):
        yield " ".join(span[1].split())


def cosim_commands(markdown: str) -> list[str]:
    """The `cosim ...` commands shown: lines and spans that start with `cosim ` (or run it under xvfb-run), and
    each `cosim ...` part of a line that chains commands with `&&`."""
    found = []
    for text in code_texts(markdown):
        for part in text.split("&&"):
            part = WRAPPER.sub("", part.strip())
            if part.startswith("cosim "):
                found.append(part)
    return found


class _ParseError(Exception):
    pass


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # type: ignore[override]  # raise instead of exiting
        raise _ParseError(message)


def parser_for(command: str) -> _Parser:
    """The parser `cosim COMMAND` parses with, built as `cosim.cli.main` builds it."""
    help_text, add_arguments, _ = COMMANDS[command]
    parser = _Parser(prog=f"cosim {command}", description=help_text)
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    add_arguments(parser)
    return parser


def command_problems(line: str) -> list[str]:
    """What is wrong with one `cosim ...` command as shown: an unknown subcommand, a flag its parser lacks, or an
    argument the parser refuses (arguments left out of a command mentioned in passing are not a problem)."""
    try:
        tokens = shlex.split(line, comments=True)
    except ValueError as exc:
        return [f"{line!r}: {exc}"]
    args = tokens[1:]
    while args and args[0] in ("-v", "--verbose"):
        args = args[1:]
    if not args or re.fullmatch(r"[A-Z_]+", args[0]):  # `cosim COMMAND --help`: a placeholder
        return []
    name, rest = args[0], args[1:]
    if name not in COMMANDS:
        return [f"{line!r}: no subcommand {name!r} (there are: {', '.join(COMMANDS)})"]
    parser = parser_for(name)
    options = {s for action in parser._actions for s in action.option_strings}
    problems = [f"{line!r}: cosim {name} has no option {flag}"
                for token in rest if re.match(r"--?[A-Za-z]", token)
                for flag in [token.split("=", 1)[0]] if flag not in options]
    # An elision (`cosim sweep ... --demand X`) or a placeholder (`--shape NAME`, `--set train.seed=S`) is no
    # command line to parse; its flags are checked above.
    if problems or "..." in rest or any(PLACEHOLDER.fullmatch(token.rsplit("=", 1)[-1]) for token in rest):
        return problems
    try:
        parsed = parser.parse_args(rest)
    except _ParseError as exc:
        message = str(exc)
        # A command mentioned in passing may leave out what it needs (`cosim compare`), or end at the flag it is
        # about (`cosim evaluate --videos`); anything else the parser refuses is a problem.
        mention = message.startswith("the following arguments are required") or (
            re.search(r"expected (at least )?one argument", message) and message.startswith(f"argument {rest[-1]}"))
        if not mention:
            problems.append(f"{line!r}: {message}")
        return problems
    # Its `--set KEY=VALUE` overrides name real config keys with values they take, on the config it names.
    config = ROOT / (getattr(parsed, "config", None) or "configs/default.yaml")
    if getattr(parsed, "overrides", None) and config.is_file():
        try:
            load_config(config, parsed.overrides)
        except ConfigError as exc:
            problems.append(f"{line!r}: {exc}")
    return problems


def link_problems(page: Path) -> list[str]:
    """Relative links and images of a Markdown page whose target does not exist (relative to the page)."""
    text = FENCE.sub("", page.read_text())
    problems = []
    for target in LINK.findall(CODE_SPAN.sub("", text)):
        if re.match(r"[a-z][a-z0-9+.-]*:", target) or target.startswith("#"):
            continue  # a URL (https:, mailto:) or an anchor on the same page
        path = target.split("#", 1)[0]
        if path and not (page.parent / path).exists():
            where = page.relative_to(ROOT) if page.is_relative_to(ROOT) else page
            problems.append(f"{where}: {target} does not exist")
    return problems


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_commands_shown_are_accepted(page: Path) -> None:
    problems = [p for line in cosim_commands(page.read_text()) for p in command_problems(line)]
    assert not problems, "\n".join(problems)


def test_commands_are_found() -> None:
    """The extraction sees the README's main job (both commands of its `&&` line) and the docs' commands, so the
    test above cannot pass by finding nothing."""
    readme = cosim_commands(README.read_text())
    assert "cosim train --config configs/smoke.yaml --out runs/smoke" in readme
    assert "cosim evaluate --run runs/smoke --episodes 10" in readme
    shown = {shlex.split(c)[1] for page in PAGES for c in cosim_commands(page.read_text())}
    assert {"train", "evaluate", "replay", "build-net", "check-net", "sweep", "compare"} <= shown


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_exist(page: Path) -> None:
    problems = link_problems(page)
    assert not problems, "\n".join(problems)


def test_checks_catch_defects(tmp_path: Path) -> None:
    """A misspelt flag, an unknown subcommand, refused values, an unknown config key and missing files are each
    reported."""
    shown = "\n".join([
        "```bash",
        "pip install -e . && cosim train --config configs/smoke.yaml --episode 5",
        "```",
        "Then `cosim evalute --run runs/x`, `cosim evaluate --policy nobody`, `cosim sweep --phi 0 --seeds one`,",
        "`cosim train --set reward.weight.merge=50`, and `cosim check-net my.net.xml --suggest` (right).",
    ])
    problems = [p for line in cosim_commands(shown) for p in command_problems(line)]
    assert len(problems) == 5, problems
    assert "has no option --episode" in problems[0]
    assert "no subcommand 'evalute'" in problems[1]
    assert "invalid choice: 'nobody'" in problems[2]
    assert "invalid" in problems[3] and "'one'" in problems[3]
    assert "reward.weight" in problems[4]
    page = tmp_path / "page.md"
    (tmp_path / "there.png").write_bytes(b"")
    page.write_text("![a](there.png) ![b](missing.png) [c](https://example.org) [d](#anchor) [e](gone.md#x)\n")
    problems = link_problems(page)
    assert len(problems) == 2 and "missing.png" in problems[0] and "gone.md#x" in problems[1], problems

