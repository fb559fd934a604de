"""The docs say what the code does: every `uavsearch ...` command in README.md and docs/*.md parses with the real
argument parser (`uavsearch.cli.build_parser`, nothing run), naming only flags and choices that exist, written out
in full; every `tools/...` script and mission file they name exists; a tool's flags are ones its code declares;
`tools/reproduce.sh` accepts its options and step names (--dry-run).

Commands are read from fenced and indented code blocks (with `\\` continuations, `#` comments, `&&` / `;` / `|`
chains) and from inline code spans. A sketch (an option in `[...]`, a `<...>` or `{a,b}` slot, `...`, or an
upper-case placeholder such as SEED, N, RUN_DIR) is not parsed whole: its subcommand and every `--flag` it names
must exist, and every value it writes out must be a valid one.
"""

from __future__ import annotations

import argparse
import ast
import contextlib
import io
import os
import re
import shlex
import subprocess
from dataclasses import dataclass
from pathlib import Path

import pytest

from uavsearch.cli import build_parser

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
FENCE = re.compile(r"^\s*(```|~~~)")
SPAN = re.compile(r"(?<!`)`([^`]+)`(?!`)")
PLACEHOLDER = re.compile(r"^(?=.*[A-Z])[A-Z0-9_,.:x\[\]]+$")  # SEED, N, RUN_DIR, LAT,LON, WxH: a value left to fill
SKETCH = re.compile(r"\.\.\.|…|\[|<[^>]*>|\{[^}]*\}")
REPO_FILE = re.compile(r"(?<![\w/.])(?:tools|missions|examples)/[\w./-]*\w\.(?:py|sh|yaml|plan)\b")
REPRODUCE = "tools/reproduce.sh"


@dataclass
class Command:
    where: str  # file:line
    text: str  # the command as written (continuations joined)
    program: str  # "uavsearch", or a script's path in the repository (tools/x.py)
    argv: list[str]  # its arguments
    sketch: bool
    inline: bool = False  # an inline span names a command in prose and may leave out what it requires
    direct: bool = False  # a script run by its path, with no interpreter before it


def _segments(text: str) -> list[list[str]] | None:
    """Shell words of each simple command in `text` (split at && || ; | & and redirections); None if unbalanced."""
    lex = shlex.shlex(text, posix=True, punctuation_chars=True)
    lex.whitespace_split = True
    lex.commenters = "#"
    try:
        words = list(lex)
    except ValueError:
        return None
    out, cur, target = [], [], False
    for w in words:
        if w and all(c in "();<>|&" for c in w):
            if w.startswith((">", "<")):  # a redirection: drop its file (and the 2 of 2>&1)
                if cur and cur[-1].isdigit():
                    cur.pop()
                target = True
            else:
                out.append(cur)
                cur = []
        elif target:
            target = False
        else:
            cur.append(w)
    return [s for s in out + [cur] if s]


def _program(words: list[str]) -> tuple[str, list[str], bool] | None:
    """(program, arguments, run by its path) of `uavsearch ...`, `python -m uavsearch ...`, `[python|bash]
    tools/x.py ...` (also after `VAR=value` or behind a launcher's `--`); None for any other command."""
    if "--" in words and _program(words[words.index("--") + 1:]):  # ray job submit ... -- uavsearch ...
        return _program(words[words.index("--") + 1:])
    while words and re.match(r"^[A-Za-z_]\w*=", words[0]):
        words = words[1:]
    direct = True
    if words and re.match(r"^(python3?|\S*/python3?|bash|sh)$", words[0]):
        if words[1:3] == ["-m", "uavsearch"]:
            return "uavsearch", words[3:], False
        words, direct = words[1:], False
    if words and Path(words[0]).name == "uavsearch":
        return "uavsearch", words[1:], False
    if words and re.match(r"^(\./)?tools/\w+\.(py|sh)$", words[0]):
        return words[0].removeprefix("./"), words[1:], direct
    return None


def _commands_in(text: str, where: str, inline: bool = False) -> list[Command]:
    if not re.search(r"(^|[\s;&|(/])(uavsearch|tools/\w+\.(py|sh))(\s|$)", text):
        return []
    segments = _segments(text)
    sketch = bool(SKETCH.search(text))
    if segments is None:  # an unbalanced quote: a sketch, judged word by word
        segments, sketch = [text.split()], True
    out = []
    for words in segments:
        if found := _program(words):
            program, argv, direct = found
            if argv or program != "uavsearch":
                out.append(Command(where, text, program, argv, sketch or any(PLACEHOLDER.match(w) for w in argv),
                                   inline, direct))
    return out


def doc_commands(path: Path) -> list[Command]:
    """Every command of one markdown file that runs `uavsearch` or a script of tools/."""
    name = path.relative_to(ROOT).as_posix()
    lines = path.read_text().splitlines()
    out, prose = [], []  # prose: (line number, text) outside code blocks, for the inline spans
    fenced, i = False, 0
    while i < len(lines):
        line = lines[i]
        if FENCE.match(line):
            fenced = not fenced
            i += 1
            continue
        indented = not fenced and line.startswith("    ") and (i == 0 or not lines[i - 1].strip()
                                                             or lines[i - 1].startswith("    "))
        if fenced or (indented and not line.lstrip().startswith(("-", "*", "|"))):
            start, text = i + 1, line.strip()
            while text.endswith("\\") and i + 1 < len(lines):
                i += 1
                text = text[:-1] + " " + lines[i].strip()
            out += _commands_in(text.removeprefix("$ "), f"{name}:{start}")
        else:
            prose.append((i + 1, line))
        i += 1
    # inline spans may wrap across the lines of a paragraph
    text = "\n".join(t for _, t in prose)
    numbers = [n for n, _ in prose]
    for m in SPAN.finditer(text):
        span = " ".join(m.group(1).split())
        if re.match(r"^(\S*/)?(uavsearch|python3? -m uavsearch|(\S*python3? )?tools/\w+\.(py|sh))(\s|$)", span):
            out += _commands_in(span, f"{name}:{numbers[text.count(chr(10), 0, m.start())]}", inline=True)
    return out


def all_commands() -> list[Command]:
    return [c for path in DOCS for c in doc_commands(path)]


# --------------------------------------------------------------------------------------------------
# uavsearch ...


def _subparser(parser: argparse.ArgumentParser, argv: list[str]) -> tuple[argparse.ArgumentParser, list[str]]:
    """The (sub)parser that the leading subcommand words of argv select, and the words that selected it."""
    path = []
    for word in argv:
        subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
        if not subs or word not in subs[0].choices:
            break
        parser = subs[0].choices[word]
        path.append(word)
    return parser, path


def _actions(parser: argparse.ArgumentParser) -> dict[str, argparse.Action]:
    return {s: a for a in parser._actions for s in a.option_strings}


def _sketch_value(action: argparse.Action, value: str) -> str | None:
    """A sketch's value of a flag, or its alternatives a|b: each one written out must convert and be a choice."""
    for alt in value.strip("[]").replace("\\|", "|").split("|"):
        if not alt or PLACEHOLDER.match(alt) or SKETCH.search(alt):
            continue
        try:
            v = action.type(alt) if callable(action.type) else alt
        except (TypeError, ValueError, argparse.ArgumentTypeError):
            return f"argument {action.option_strings[0]}: invalid value {alt!r}"
        if action.choices is not None and v not in action.choices:
            return f"argument {action.option_strings[0]}: invalid choice {alt!r} (choose from {list(action.choices)})"
    return None


def _unknown_flags(words: list[str], flags, what: str) -> str | None:
    for word in words:
        flag = word.strip("[]()").split("=")[0]
        if re.match(r"^--?[a-zA-Z]", flag) and flag not in flags:
            near = sorted(f for f in flags if f.startswith(flag))
            return f"{what} has no flag {flag}" + (f" (written out: {', '.join(near)})" if near else "")
    return None


def check(command: Command, parser: argparse.ArgumentParser) -> str | None:
    """None if a `uavsearch` command holds, else what is wrong with it."""
    sub, path = _subparser(parser, command.argv)
    if not path and not all(w.startswith("-") for w in command.argv):
        return None if PLACEHOLDER.match(command.argv[0]) else f"no subcommand {command.argv[0]!r}"
    actions = {**_actions(parser), **_actions(sub)}
    words = command.argv[len(path):]
    if msg := _unknown_flags(words, actions, f"`uavsearch {' '.join(path)}`"):
        return msg
    for i, word in enumerate(words):
        flag = word.strip("[]()").split("=")[0]
        value = word.split("=", 1)[1] if "=" in word else (words[i + 1] if i + 1 < len(words) else "")
        if (command.sketch and flag in actions and actions[flag].nargs != 0 and value
                and not value.startswith(("-", "[-"))):
            if msg := _sketch_value(actions[flag], value):
                return msg
    if command.sketch:
        return None
    err, out = io.StringIO(), io.StringIO()
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
            parser.parse_args(command.argv)
    except SystemExit as e:
        msg = err.getvalue().strip().splitlines()[-1] if e.code else None
        if msg and command.inline and re.search(r"arguments are required|expected (at least )?one argument", msg):
            return None  # `uavsearch eval team` or `uavsearch fly --connect` named in a sentence
        return msg
    return None


# --------------------------------------------------------------------------------------------------
# tools/...


def tool_flags(script: Path) -> set[str] | None:
    """The flags a tool's code declares (add_argument literals in it and in the uavsearch.research modules it
    runs); None where it declares them some other way."""
    flags, todo, seen = set(), [script], set()
    while todo:
        path = todo.pop()
        if path in seen or not path.is_file():
            continue
        seen.add(path)
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call) and getattr(node.func, "attr", None) == "add_argument":
                flags |= {a.value for a in node.args if isinstance(a, ast.Constant) and str(a.value).startswith("-")}
            elif isinstance(node, ast.Call) and getattr(node.func, "id", None) == "add_dataclass_args":
                return None
            elif isinstance(node, ast.ImportFrom):
                mod = node.module or ""
                if node.level == 1 and path.parent.name == "research":
                    todo.append(path.parent / f"{mod}.py")
                elif mod.startswith("uavsearch.research."):
                    todo.append(ROOT / (mod.replace(".", "/") + ".py"))
    return flags | {"-h", "--help"} if flags else None


def check_tool(command: Command) -> str | None:
    script = ROOT / command.program
    if not script.is_file():
        return f"no script {command.program}"
    if command.direct and not command.inline and not os.access(script, os.X_OK):
        return f"{command.program} is not executable: write `python {command.program}`"
    if command.program == REPRODUCE:
        if command.sketch or command.inline and not command.argv:
            return None
        r = subprocess.run(["bash", str(script), *command.argv, "--dry-run"], capture_output=True, text=True,
                           timeout=60, cwd=ROOT)
        return None if r.returncode == 0 else (r.stderr.strip() or r.stdout.strip()).splitlines()[-1]
    flags = tool_flags(script) if script.suffix == ".py" else None
    return _unknown_flags(command.argv, flags, command.program) if flags is not None else None


# --------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def parser() -> argparse.ArgumentParser:
    return build_parser()


def test_commands_are_found_in_blocks_spans_and_continuations(tmp_path, monkeypatch):
    doc = tmp_path / "x.md"
    doc.write_text("Run `uavsearch fly --scene 3`, or\n`uavsearch\nsitl --speed max`.\n\n```bash\n"
                   "uavsearch eval search --setting 2 \\\n    --episodes 5  # a comment\n"
                   "cd x && python -m uavsearch replay runs/a --out b > log.txt 2>&1\n"
                   "ray job submit -- uavsearch train map --budget 8\n```\n\n"
                   "    uavsearch fly [--scene SEED]\n    .venv/bin/python tools/seed_spread.py a --out b\n")
    monkeypatch.setattr("test_docs_commands.ROOT", tmp_path)
    got = [(c.where, c.program, c.argv, c.sketch) for c in doc_commands(doc)]
    assert got == [("x.md:6", "uavsearch", ["eval", "search", "--setting", "2", "--episodes", "5"], False),
                   ("x.md:8", "uavsearch", ["replay", "runs/a", "--out", "b"], False),
                   ("x.md:9", "uavsearch", ["train", "map", "--budget", "8"], False),
                   ("x.md:12", "uavsearch", ["fly", "[--scene", "SEED]"], True),
                   ("x.md:13", "tools/seed_spread.py", ["a", "--out", "b"], False),
                   ("x.md:1", "uavsearch", ["fly", "--scene", "3"], False),
                   ("x.md:2", "uavsearch", ["sitl", "--speed", "max"], False)]


def test_an_unknown_flag_a_bad_choice_and_a_shortened_flag_are_caught(parser):
    def c(text, sketch=False):
        return check(Command("x.md:1", text, "uavsearch", text.split(), sketch), parser)

    assert c("fly --scene 3") is None
    assert "--train-views" in c("eval search --train-views 3")
    assert "invalid choice" in c("eval search --vehicle boat")
    assert "--mission-time" in c("fly --mission-tim 80")
    assert "--bogus" in c("fly [--bogus N]", sketch=True)
    assert c("fly [--scene SEED] [--speed 1|N|max]", sketch=True) is None
    assert "'fast'" in c("fly [--speed 1|fast]", sketch=True)
    assert "'boat'" in c("eval search --vehicle mavlink|boat --out DIR", sketch=True)


def test_a_tools_flags_and_reproduce_steps_are_checked():
    def c(text):
        program, *argv = text.split()
        return check_tool(Command("x.md:1", text, program, argv, False))

    assert "--budget" in tool_flags(ROOT / "tools/wide_fusion_probe.py")  # declared in the probe it imports
    assert c("tools/wide_fusion_probe.py --budget 8 --no-symmetries") is None
    assert "--train-views" in c("tools/wide_fusion_probe.py --train-views 8")
    assert "no script" in c("tools/no_such_tool.py")
    assert "not executable" in check_tool(Command("x.md:1", "", "tools/seed_spread.py", [], False, direct=True))
    assert check_tool(Command("x.md:1", "", "tools/seed_spread.py", [], False, direct=False)) is None
    assert c("tools/reproduce.sh --only search") is None
    assert "unknown step" in c("tools/reproduce.sh --only no_such_step")


def test_docs_commands_parse(parser):
    commands = [c for c in all_commands() if c.program == "uavsearch"]
    assert len(commands) > 50, "the docs' commands were not found"
    bad = [f"{c.where}: {c.text}\n    {msg}" for c in commands if (msg := check(c, parser))]
    assert not bad, "commands in the docs that the CLI refuses:\n" + "\n".join(bad)


def test_docs_tool_commands_hold():
    commands = [c for c in all_commands() if c.program != "uavsearch"]
    assert len(commands) > 20, "the docs' tool commands were not found"
    bad = [f"{c.where}: {c.text}\n    {msg}" for c in commands if (msg := check_tool(c))]
    assert not bad, "tool commands in the docs that do not hold:\n" + "\n".join(bad)


def test_docs_name_only_files_that_exist():
    missing = []
    for path in DOCS:
        for n, line in enumerate(path.read_text().splitlines(), 1):
            missing += [f"{path.relative_to(ROOT)}:{n}: {t}" for t in REPO_FILE.findall(line)
                        if not (ROOT / t).is_file()]
    assert not missing, "the docs name files that do not exist: " + "; ".join(missing)


def _mission_row(field: str) -> str:
    """The meaning cell of a field of docs/reference.md's mission table."""
    for line in (ROOT / "docs" / "reference.md").read_text().splitlines():
        if line.startswith(f"| `{field}`"):
            return line.replace("\\|", "/").split("|")[2]  # an escaped \| is a / inside the cell
    raise AssertionError(f"docs/reference.md has no mission row `{field}`")


def test_reference_names_every_policy_and_fusion_a_paper_mission_takes():
    from uavsearch.search.agents import POLICIES
    from uavsearch.search.fusion import FUSIONS

    def missing(names, cell):
        return [n for n in names if not re.search(rf"(?<!\w){re.escape(n)}(?!\w)", cell)]

    policies = [n for n, kind in POLICIES.items() if getattr(kind, "move_set", None) != "any"]
    fusions = [n for n, cls in FUSIONS.items() if not getattr(cls, "fitted", False)]
    assert not missing(policies, _mission_row("policy")), "docs/reference.md's `policy` row lacks some"
    assert not missing(fusions, _mission_row("fusion")), "docs/reference.md's `fusion` row lacks some"
