"""The documentation against the code: the method's sections that the code cites, every command line and quoted
default against the parser, every public name in the API reference, and the README's links."""

from __future__ import annotations

import argparse
import importlib
import re
import shlex
from dataclasses import dataclass
from pathlib import Path

import pytest

import cvqpg
from cvqpg.cli import build_parser

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
PAGES = (README, *sorted((ROOT / "docs").rglob("*.md")))
FENCE = re.compile(r"^```(\w*)\n(.*?)^```", re.MULTILINE | re.DOTALL)
# A command or program named in the text: `cvqpg SUB ...`, or a script of the repository.
MENTION = re.compile(r"`(?:\.venv/bin/)?cvqpg (\w[\w-]*)|(?:benchmarks|scripts)/\w+\.(?:py|sh)")
# "`--flag ...` (default X)" and "`--flag`, default `X`": a default quoted beside its flag.
QUOTED_DEFAULT = re.compile(r"`(--[\w-]+)[^`]*`,?\s+\(?default:?\s+(?:`([^`]+)`|([\w./-]+))")


def cited_sections() -> dict[str, set[int]]:
    cited: dict[str, set[int]] = {}
    for path in sorted((ROOT / "cvqpg").rglob("*.py")):
        for first, last in re.findall(r"method\.md §(\d+)(?:–§(\d+))?", path.read_text()):
            cited.setdefault(str(path.relative_to(ROOT)), set()).update(range(int(first), int(last or first) + 1))
    return cited


def test_code_cites_the_method_document_by_existing_sections():
    sections = {int(n) for n in re.findall(r"^## (\d+)\. ", (ROOT / "docs" / "method.md").read_text(), re.MULTILINE)}
    cited = cited_sections()
    assert len(cited) >= 10  # the kernels, optics, loss, fitting and metrics all cite it
    assert {path: numbers - sections for path, numbers in cited.items() if numbers - sections} == {}


def test_no_code_cites_a_document_outside_the_repository():
    assert [str(p) for p in (ROOT / "cvqpg").rglob("*.py") if re.search(r"\bSPEC\b(?!TRUM)", p.read_text())] == []


# Command lines.

def subparsers() -> dict[str, argparse.ArgumentParser]:
    parser = build_parser()
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return {"": parser, **action.choices}


def prose(text: str) -> str:
    """`text` without its fenced code blocks (replaced by blank lines, so that line numbers hold)."""
    return FENCE.sub(lambda m: "\n" * m.group(0).count("\n"), text)


def line_of(text: str, index: int) -> int:
    return text.count("\n", 0, index) + 1


def cvqpg_arguments(tokens: list[str]) -> list[list[str]]:
    """The argument lists of the cvqpg commands among `tokens` (one shell command line), those quoted inside
    another command (`sbatch --wrap '...'`) included: `cvqpg` where a command starts, not as a word in one."""
    found = []
    for i, token in enumerate(tokens):
        starts = i == 0 or tokens[i - 1] in ("&&", ";", "|") or re.fullmatch(r"[A-Z_]+=[^'\"\s]*", tokens[i - 1])
        if starts and (token == "cvqpg" or token.endswith("/cvqpg")):
            arguments = tokens[i + 1:]
            found.append(arguments[:next((j for j, t in enumerate(arguments) if t in ("&&", ";", "|")),
                                         len(arguments))])
        elif token == "-m" and tokens[i + 1:i + 2] == ["cvqpg.cli"]:
            found.extend(cvqpg_arguments(["cvqpg", *tokens[i + 2:]]))
        elif " " in token and "cvqpg " in token:
            found.extend(cvqpg_arguments(split(token)))
    return found


def split(command: str) -> list[str]:
    """A shell line's words; a line that opens a quote it closes on a later line, as words between spaces."""
    lexer = shlex.shlex(command.replace("\\|", "|"), posix=True, punctuation_chars="&;|")
    lexer.whitespace_split, lexer.commenters = True, "#"
    try:
        return list(lexer)
    except ValueError:
        return command.split()


def command_lines() -> list[tuple[str, list[str]]]:
    """(where, arguments) of every cvqpg command in the README and the docs: the lines of their shell code
    blocks (with continuations) and their inline `cvqpg ...` spans."""
    found = []
    for page in PAGES:
        text = page.read_text()
        name = str(page.relative_to(ROOT))
        for block in FENCE.finditer(text):
            if block.group(1) not in ("bash", "sh", "console", ""):
                continue
            start = line_of(text, block.start(2))
            lines = block.group(2).replace("\\\n", "  ").split("\n")
            for offset, line in enumerate(lines):
                found += [(f"{name}:{start + offset}", arguments) for arguments in cvqpg_arguments(split(line))]
        text = prose(text)
        for span in re.finditer(r"`((?:\.venv/bin/)?cvqpg [^`]+)`", text):
            found += [(f"{name}:{line_of(text, span.start())}", arguments)
                      for arguments in cvqpg_arguments(split(span.group(1)))]
    return found


COMMANDS = command_lines()


def test_the_docs_have_command_lines():
    assert {where.split(":")[0] for where, _ in COMMANDS} >= {"README.md", "docs/cli.md", "docs/compression.md"}


@pytest.mark.parametrize("where, arguments", COMMANDS, ids=[where for where, _ in COMMANDS])
def test_command_line_uses_the_parser_s_subcommand_and_flags(where, arguments):
    parsers = subparsers()
    command = "" if not arguments or arguments[0].startswith("-") else arguments[0]
    assert command in parsers, f"{where}: cvqpg has no subcommand {command!r}"
    options = parsers[command]._option_string_actions
    flags = [a.split("=")[0] for a in arguments if a.startswith("--") or a == "-h"]
    assert [flag for flag in flags if flag not in options] == [], f"{where}: cvqpg {command}: unknown flags"


# Quoted defaults.

@dataclass(frozen=True)
class QuotedDefault:
    where: str
    command: str | None  # None: no command named; every subcommand that has the flag must agree
    flag: str
    value: str


def context(text: str, index: int) -> str | None:
    """The subcommand that the text at `index` speaks of: the nearest one named before it in its paragraph or
    list item, else in its section's heading, else in the page's title; "script" where the nearest is a script,
    None where none is named. A table speaks of what the paragraph before it names."""
    while text.startswith("|", text.rfind("\n", 0, index) + 1):  # from a table's row to the text before it
        index = text.rfind("\n", 0, index)
    section = max(text.rfind("\n#", 0, index), 0)
    paragraph = max([m.end() for m in re.finditer(r"\n\s*\n|\n\s*(?:[-*]|\d+\.) ", text[:index])] + [section])
    for scope in (text[paragraph:index], text[section:text.find("\n", section + 1)], text[:text.find("\n")]):
        mentions = list(MENTION.finditer(scope))
        if mentions:
            return mentions[-1].group(1) or "script"
    return None


def quoted_defaults() -> list[QuotedDefault]:
    found = []
    for page in PAGES:
        text = prose(page.read_text())
        name = str(page.relative_to(ROOT))
        for match in QUOTED_DEFAULT.finditer(text):
            found.append(QuotedDefault(f"{name}:{line_of(text, match.start())}", context(text, match.start()),
                                       match.group(1), match.group(2) or match.group(3)))
        for table in re.finditer(r"^\|.*\|\n\|[-| ]+\|\n(?:\|.*\|\n?)+", text, re.MULTILINE):
            rows = [[cell.strip() for cell in row.strip("|").split(" | ")] for row in table.group(0).splitlines()]
            if "default" not in [cell.lower() for cell in rows[0]]:
                continue
            column = [cell.lower() for cell in rows[0]].index("default")
            command = context(text, table.start())
            for offset, row in enumerate(rows[2:], 2):
                flag = re.search(r"--[\w-]+", row[0])
                value = re.fullmatch(r"`([^`]+)`", row[column]) if column < len(row) else None
                if flag and value:
                    found.append(QuotedDefault(f"{name}:{line_of(text, table.start()) + offset}", command,
                                               flag.group(0), value.group(1)))
    return found


def agrees(value: str, action: argparse.Action) -> bool:
    """Whether `value`, as the docs quote it, is `action`'s default: its value (numbers compared as numbers), or,
    where the parser leaves it to the library (None), what the help text says."""
    default = action.default
    if default is None or default is argparse.SUPPRESS:
        return value in (action.help or "")
    expected = [str(v) for v in default] if isinstance(default, (list, tuple)) else [str(default)]
    given = value.split()
    if len(given) != len(expected):
        return False
    for g, e in zip(given, expected):
        try:
            if float(g) != float(e):
                return False
        except ValueError:
            if g != e:
                return False
    return True


DEFAULTS = [quoted for quoted in quoted_defaults() if quoted.command != "script"]


def test_the_docs_quote_defaults():
    assert len(DEFAULTS) >= 15


@pytest.mark.parametrize("quoted", DEFAULTS, ids=[f"{q.where} {q.flag}" for q in DEFAULTS])
def test_quoted_default_is_the_parser_s(quoted):
    parsers = subparsers()
    if quoted.command is not None:
        assert quoted.command in parsers, f"{quoted.where}: cvqpg has no subcommand {quoted.command!r}"
    names = [quoted.command] if quoted.command is not None else [n for n in parsers if n]
    actions = {name: parsers[name]._option_string_actions.get(quoted.flag) for name in names}
    actions = {name: action for name, action in actions.items() if action is not None}
    assert actions, f"{quoted.where}: no subcommand {quoted.command or ''} has {quoted.flag}"
    wrong = {name: action.default for name, action in actions.items() if not agrees(quoted.value, action)}
    assert wrong == {}, f"{quoted.where}: {quoted.flag} quoted with default {quoted.value!r}"


# The API reference and the pages themselves.

def test_every_public_name_has_one_reference_entry():
    documented = [path for page in sorted((ROOT / "docs" / "api").glob("*.md"))
                  for path in re.findall(r"^::: ([\w.]+)$", page.read_text(), re.MULTILINE)]
    public = sorted(name for name in cvqpg.__all__ if not name.startswith("_"))
    assert sorted(path.rsplit(".", 1)[1] for path in documented) == public
    # Each entry documents the very object that `cvqpg` exports.
    assert [path for path in documented if getattr(importlib.import_module(path.rsplit(".", 1)[0]),
                                                   path.rsplit(".", 1)[1]) is not getattr(cvqpg, path.rsplit(".", 1)[1])
            ] == []


def test_no_issue_numbers_in_the_docs():
    assert [f"{page.relative_to(ROOT)}:{line_of(page.read_text(), m.start())}"
            for page in PAGES for m in re.finditer(r"#[0-9]{2}|\bissue [0-9]+", page.read_text())] == []


def test_the_readme_is_short_and_its_links_resolve():
    text = README.read_text()
    assert text.count("\n") <= 200
    links = re.findall(r"\]\(([^)#]+)(?:#[^)]*)?\)", text)
    assert links and [link for link in links if "://" not in link and not (ROOT / link).exists()] == []
