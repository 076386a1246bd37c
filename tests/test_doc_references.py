"""The documentation names things that exist: README.md, docs/*.md and models/MODEL_CARD.md
checked against the repository and the code.

* Links: every relative markdown link (and image) target is a file or folder of the repository,
  and an anchor in a link to a markdown file (``MODEL_CARD.md#uncertainty``) is one of its headings.
* Paths: every path in a code span that names a top-level folder of the repository
  (``polrig/``, ``drivers/``, ``calibration/``, ``models/``, ``sim/``, ``tests/``,
  ``benchmarks/``, ``docs/``) or ends in a file extension exists, as spelled, from the
  repository root. These are repository paths: ``calibration/dofp.py``, not the installed
  ``polrig/calibration/dofp.py`` (pyproject.toml's package-dir maps the folders).
* Python names: every ``polrig.a.b.c`` in a code span or a ```python block (and the modules
  and names a ```python block imports) resolves: the longest importable module prefix, then
  attributes; keywords in a call spelled right after it (``evaluate(methods=...)``) are
  parameters of the callable. A module whose import fails for want of a third-party package (an
  optional extra) is skipped, and the test says so; an import failing in polrig itself fails.
* Commands: every ``polrig COMMAND [SUB] --option [VALUE]`` in a code span or a shell block
  names a real sub-command (the parser of :func:`polrig.cli.build_parser`), options that
  sub-command accepts, values among an option's or a positional's choices where it has them;
  every ``python -m benchmarks NAME`` names a benchmark the runner knows.

Placeholders (``DIR``, ``RESULT.exr``, ``<size>``, ``...``), globs, paths under ``runs/`` or
``/tmp``, and absolute paths are not references and are skipped; :data:`ALLOWED` lists the few
spans that look like references but are not, each with its reason.
"""

from __future__ import annotations

import argparse
import functools
import importlib
import importlib.util
import inspect
import pathlib
import re
import shlex
import warnings
from dataclasses import dataclass

REPO = pathlib.Path(__file__).resolve().parents[1]
DOCS = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md")), REPO / "models" / "MODEL_CARD.md"]
TOP_FOLDERS = ("polrig", "drivers", "calibration", "models", "sim", "tests", "benchmarks", "docs")

#: Code-span words that look like references and are not: word -> why.
ALLOWED = {
    "include/mitsuba/render/mueller.h": "a path in Mitsuba 3's source tree, not this repository's",
    "models/weights/large/": "where the large size is shipped once trained on a GPU lease "
                             "(polrig.models.sizes.is_shipped); not in this repository yet",
    "polrig.session": "docs/architecture.md names it as an old path the architecture test refuses",
    "polrig.api": "docs/architecture.md names it as the alternative that was not built",
    "polrig.models.runtime.infer_frame": "MODEL_CARD.md names it as the function of then, "
                                         "beside today's polrig.app.single_shot.SingleShot.frame",
}


@dataclass(frozen=True)
class Span:
    """Code from a document: an inline code span, or one line of a fenced block."""

    doc: pathlib.Path
    line: int
    text: str
    block: str | None  # the fenced block's language ("" for none); None for an inline span

    def where(self) -> str:
        return f"{self.doc.relative_to(REPO)}:{self.line}"


# ---------------------------------------------------------------------------------------------
# Reading the documents


_FENCE = re.compile(r"^ {0,3}(`{3,}|~{3,})\s*([\w+-]*)")
_INLINE = re.compile(r"(?<!`)(`+)(?!`)(.+?)(?<!`)\1(?!`)", re.S)
_LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\[\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)", re.S)


@functools.cache
def _parsed(doc: pathlib.Path) -> tuple[str, tuple[Span, ...]]:
    """The document's prose with its code spans blanked out (for links), and its code."""
    lines = doc.read_text(encoding="utf-8").splitlines()
    prose, code = [], []
    fence = lang = None
    for n, line in enumerate(lines, 1):
        m = _FENCE.match(line)
        if fence is None and m:
            fence, lang = m.group(1), m.group(2).lower()
            prose.append("")
        elif fence is not None:
            if line.strip().startswith(fence[0] * len(fence)) and not line.strip().strip(fence[0]):
                fence = None
            else:
                code.append(Span(doc, n, line, lang))
            prose.append("")
        else:
            prose.append(line)
    text = "\n".join(prose)
    for m in _INLINE.finditer(text):
        line = text.count("\n", 0, m.start()) + 1
        code.append(Span(doc, line, m.group(2).replace("\n", " ").replace("\\|", "|").strip(), None))
    blanked = _INLINE.sub(lambda m: re.sub(r"[^\n]", " ", m.group(0)), text)
    return blanked, tuple(code)


def _spans(*, inline: bool = True, blocks: tuple[str, ...] = ()) -> list[Span]:
    return [s for doc in DOCS for s in _parsed(doc)[1]
            if (s.block is None and inline) or (s.block is not None and s.block in blocks)]


def _is_placeholder(word: str) -> bool:
    """``DIR``, ``OUT.zarr``, ``RESULT_OR_SESSION``, ``FILE.exr``: a name the reader fills in."""
    stem = word.split(".")[0]
    return bool(re.fullmatch(r"[A-Z][A-Z0-9_]*", stem))


# ---------------------------------------------------------------------------------------------
# (a) links


@functools.cache
def _anchors(doc: pathlib.Path) -> frozenset[str]:
    """The anchors of a markdown file's headings, as GitHub makes them (lower case, punctuation
    dropped, spaces to hyphens, ``-1``, ``-2`` for repeats)."""
    anchors, fence = set(), False
    for line in doc.read_text(encoding="utf-8").splitlines():
        fence ^= bool(_FENCE.match(line))
        m = None if fence else re.match(r"#{1,6}\s+(.*?)\s*#*\s*$", line)
        if m:
            slug = re.sub(r"[^\w\- ]", "", m.group(1).lower()).replace(" ", "-")
            n = 0
            while (slug + (f"-{n}" if n else "")) in anchors:
                n += 1
            anchors.add(slug + (f"-{n}" if n else ""))
    return frozenset(anchors)


def test_relative_links_exist():
    checked, missing = 0, []
    for doc in DOCS:
        prose = _parsed(doc)[0]
        for m in _LINK.finditer(prose):
            target = m.group(1)
            if re.match(r"[a-z][a-z0-9+.-]*:", target):
                continue  # a URL (http:, mailto:)
            path, _, anchor = target.partition("#")
            file = (doc.parent / path) if path else doc
            checked += 1
            where = f"{doc.relative_to(REPO)}:{prose.count(chr(10), 0, m.start()) + 1}"
            if not file.exists():
                missing.append(f"{where}: link to {target}")
            elif anchor and file.suffix == ".md" and anchor not in _anchors(file):
                missing.append(f"{where}: link to {target}: {path or doc.name} has no heading #{anchor}")
    assert checked > 50, checked
    assert not missing, "link targets that do not exist:\n" + "\n".join(missing)


# ---------------------------------------------------------------------------------------------
# (b) repository paths


_PATH = re.compile(r"[\w.@+-]+(?:/[\w.@+-]+)*/?")
_EXTENSION = re.compile(r"\.[A-Za-z][A-Za-z0-9]{0,5}$")


def _repository_paths(span: Span) -> list[str]:
    paths = []
    words = span.text.split()
    for before, word in zip(["", *words], words):
        if before in ("--out", "-o"):
            continue  # what a command writes
        word = word.strip("()[]{},;:'\"").removesuffix(".")  # punctuation around a path
        word = re.sub(r":\d+(-\d+)?$", "", word)  # file.py:123
        if "/" not in word or not _PATH.fullmatch(word) or word in ALLOWED:
            continue
        first = word.split("/")[0]
        if word.startswith(("/", "~", "..", "runs/")) or _is_placeholder(first):
            continue  # absolute, outside the repository, example output, or a placeholder
        if first in TOP_FOLDERS or _EXTENSION.search(word.rstrip("/")):
            paths.append(word)
    return paths


def test_repository_paths_exist():
    checked, missing = 0, []
    for span in _spans():
        for path in _repository_paths(span):
            checked += 1
            if not (REPO / path).exists():
                hint = ""
                first, _, rest = path.partition("/")
                if first == "polrig" and rest.split("/")[0] in ("drivers", "sim", "calibration", "models"):
                    hint = f" (in the repository: {rest})"
                missing.append(f"{span.where()}: {path}{hint}")
    assert checked > 100, checked
    assert not missing, "paths that do not exist in the repository:\n" + "\n".join(missing)


# ---------------------------------------------------------------------------------------------
# (c) Python names


_DOTTED = re.compile(r"(?<![\w.])polrig(?:\.[A-Za-z_]\w*)+")
_IMPORT = re.compile(r"^\s*(?:from\s+([\w.]+)\s+import\s+\(?([\w\s,]+?)\)?\s*(?:#.*)?$"
                     r"|import\s+([\w.]+)(?:\s+as\s+\w+)?\s*(?:#.*)?$)")
_AS = re.compile(r"\s+as\s+\w+")
_OLD_TOP_LEVEL = ("drivers", "sim", "calibration", "models")


class _MissingExtra(Exception):
    """The module needs a third-party package that is not installed (an optional extra)."""


@functools.cache
def _import(module: str):
    """The module, None if there is no such module, or _MissingExtra."""
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as exc:
        if exc.name and (module == exc.name or module.startswith(exc.name + ".")):
            return None  # this module (or a package above it) does not exist
        if exc.name and exc.name.split(".")[0] != "polrig":
            return _MissingExtra(f"{module} needs {exc.name}")
        raise


def _resolve(dotted: str):
    """The object ``dotted`` names; raises LookupError (naming the missing part) or _MissingExtra."""
    parts = dotted.split(".")
    for i in range(len(parts), 0, -1):
        obj = _import(".".join(parts[:i]))
        if isinstance(obj, _MissingExtra):
            raise obj
        if obj is not None:
            break
    else:
        raise LookupError(f"no module {parts[0]}")
    for j in range(i, len(parts)):
        try:
            obj = getattr(obj, parts[j])
        except AttributeError:
            raise LookupError(f"{'.'.join(parts[:j])} has no {parts[j]!r}") from None
    return obj


def _keywords(text: str) -> list[str]:
    """Keyword arguments in the call that ``text`` starts with: ``(a, b=1, c=...)`` -> b, c."""
    if not text.startswith("("):
        return []
    depth, end = 0, len(text)
    for k, ch in enumerate(text):
        depth += ch in "([{"
        depth -= ch in ")]}"
        if depth == 0:
            end = k
            break
    inner = text[1:end]
    return re.findall(r"(?:^|[(,]\s*)([A-Za-z_]\w*)\s*=(?!=)", re.sub(r"\([^()]*\)", "()", inner))


def _python_names() -> list[tuple[Span, str, list[str]]]:
    """(span, dotted name, keywords of a call spelled after it)."""
    names = []
    for span in _spans(blocks=("python", "py")):
        for m in _DOTTED.finditer(span.text):
            names.append((span, m.group(0), _keywords(span.text[m.end():])))
        if span.block:
            m = _IMPORT.match(_AS.sub("", span.text))
            if m and m.group(1):
                names += [(span, f"{m.group(1)}.{n.strip()}", []) for n in m.group(2).split(",") if n.strip()]
            elif m and m.group(3):
                names.append((span, m.group(3), []))
    return names


def test_python_names_resolve():
    checked, missing, skipped = 0, [], []
    for span, dotted, keywords in _python_names():
        top = dotted.split(".")[0]
        if top in _OLD_TOP_LEVEL:
            checked += 1
            missing.append(f"{span.where()}: {dotted}: installed as polrig.{dotted}")
            continue
        if top != "polrig" or dotted in ALLOWED:
            continue  # numpy, zarr, ...: not ours
        checked += 1
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                obj = _resolve(dotted)
        except _MissingExtra as exc:
            skipped.append(f"{span.where()}: {dotted} ({exc})")
            continue
        except LookupError as exc:
            missing.append(f"{span.where()}: {dotted}: {exc}")
            continue
        if keywords:
            try:
                params = inspect.signature(obj).parameters
            except (TypeError, ValueError):
                continue  # a builtin without a signature
            if not any(p.kind is p.VAR_KEYWORD for p in params.values()):
                missing += [f"{span.where()}: {dotted}: no parameter {k!r}" for k in keywords if k not in params]
    if skipped:  # an optional extra is not installed here: those names are not checked
        warnings.warn("not checked (optional extra not installed):\n" + "\n".join(skipped))
    assert checked > 100, checked
    assert not missing, "Python names that do not resolve:\n" + "\n".join(missing)


# ---------------------------------------------------------------------------------------------
# (d) commands


_COMMAND = re.compile(r"(?:^|&&|;|\s\|)\s*(?:\S*/)?(?:polrig|python3? -m polrig)\s+(?=[\w{.-])")
_BENCHMARKS = re.compile(r"(?:^|\s)\S*python3? -m benchmarks((?:\s+[^\s-][^\s]*)*)")


@functools.cache
def _parser() -> argparse.ArgumentParser:
    from polrig.cli import build_parser

    return build_parser()


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    return next((dict(a.choices) for a in parser._actions if isinstance(a, argparse._SubParsersAction)), {})


def _alternatives(word: str) -> list[str]:
    """``{a,b}`` or ``a|b`` or ``a/b`` -> [a, b] (literal alternatives only)."""
    word = word.strip("[]")
    if word.startswith("{") and word.endswith("}"):
        return word[1:-1].split(",")
    return [w for w in re.split(r"[|/]", word) if w]


def _literal(word: str) -> bool:
    """A value spelled out, not a placeholder (``N``, ``DIR``, ``...``, ``<x>``)."""
    return bool(re.fullmatch(r"[a-z0-9][\w.,:+-]*", word)) and not _is_placeholder(word)


def _command_words(text: str) -> list[str]:
    """The words of one command line: up to a comment, ``;``, ``&&`` or a pipe (`` | ``)."""
    text = re.split(r"\s#|;|&&|\s\|\s|\s>|\$\(", text)[0]
    try:
        words = shlex.split(text)
    except ValueError:  # an unbalanced quote in a shortened example
        words = text.split()
    return [w for w in words if w not in ("[", "]", "\\", "|")]


def _check_command(words: list[str]) -> list[str]:
    """What is wrong with ``polrig WORDS`` (empty when nothing is)."""
    problems = []
    parsers = [("polrig", _parser())]
    any_of = False  # `polrig calibrate ... --x`: one of the sub-commands accepts --x
    i = 0
    while i < len(words) and (subs := _subparsers(parsers[0][1])):
        word = words[i]
        if word.startswith("-") or word.startswith("["):
            break
        if word in ("...", "COMMAND", "SUBCOMMAND"):
            parsers = [(f"{p} {n}", s) for p, q in parsers for n, s in _subparsers(q).items()]
            any_of = True
        else:
            names = _alternatives(word)
            unknown = [n for n in names if n not in subs]
            if unknown:
                return [f"{parsers[0][0]}: no sub-command {', '.join(unknown)} "
                        f"(there are: {', '.join(subs)})"]
            parsers = [(f"{p} {n}", _subparsers(s)[n]) for p, s in parsers for n in names]
        i += 1
    positional = 0
    while i < len(words):
        word = words[i].strip("[]")
        i += 1
        if word.startswith("-") and len(word) > 1 and not re.fullmatch(r"-[\d.]+", word):
            for option in re.split(r"[/|]", word):
                option = option.strip("[]").split("=")[0]
                if not option:
                    continue
                actions = [p._option_string_actions.get(option) for _, p in parsers]
                accepted = any(actions) if any_of else all(actions)
                if not accepted:
                    where = " or ".join(n for n, _ in parsers) if any_of else \
                        ", ".join(n for (n, _), a in zip(parsers, actions) if a is None)
                    problems.append(f"{where}: no option {option}")
                    continue
                takes = [(n, a) for (n, _), a in zip(parsers, actions) if a is not None]
                if all(a.nargs == 0 for _, a in takes) or re.search("[=/|]", word) or i >= len(words):
                    continue  # no value, a value after '=', or `--a/--b` (options named, no value)
                value = words[i]
                if not value.lstrip("[").startswith("-"):
                    i += 1
                    wrong = [_check_choices(a, value, f"{n} {option}") for n, a in takes]
                    problems += [p for w in wrong for p in w] if not any_of or all(wrong) else []
        else:
            for name, p in parsers:
                slots = [a for a in p._actions if not a.option_strings
                         and not isinstance(a, argparse._SubParsersAction)]
                if positional < len(slots) and slots[positional].nargs is None:
                    problems += _check_choices(slots[positional], word, name)
            positional += 1
    return problems


def _check_choices(action: argparse.Action, value: str, where: str) -> list[str]:
    if action.choices is None or (value.startswith("[") and not value.endswith("}")):
        return []  # free values, or an optional group `[--x N]` rather than a value
    choices = {str(c) for c in action.choices}
    return [f"{where}: {v!r} is not one of {', '.join(sorted(choices))}"
            for v in _alternatives(value) if _literal(v) and v not in choices]


def _commands() -> list[tuple[Span, list[str]]]:
    found = []
    for span in _spans(blocks=("bash", "sh", "shell", "console", "")):
        if span.block is not None and span.text.lstrip().startswith("#"):
            continue
        for m in _COMMAND.finditer(span.text):
            found.append((span, _command_words(span.text[m.end():])))
    return found


def test_commands_and_options_exist():
    commands = _commands()
    problems = [f"{span.where()}: `{span.text}`: {p}" for span, words in commands for p in _check_command(words)]
    assert len(commands) > 100, len(commands)
    assert not problems, "commands the parser does not accept:\n" + "\n".join(problems)


@functools.cache
def _benchmarks() -> set[str]:
    spec = importlib.util.spec_from_file_location("_benchmarks_runner", REPO / "benchmarks" / "__main__.py")
    runner = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(runner)
    return set(runner.available())


def test_benchmark_names_exist():
    checked, missing = 0, []
    for span in _spans(blocks=("bash", "sh", "shell", "console", "")):
        for m in _BENCHMARKS.finditer(span.text):
            for name in m.group(1).split():
                name = name.strip("[]")
                if not _literal(name):
                    continue
                checked += 1
                key = pathlib.Path(name).stem.removeprefix("bench_")
                if key not in _benchmarks():
                    missing.append(f"{span.where()}: python -m benchmarks {name}")
    assert checked > 10, checked
    assert not missing, ("benchmarks that do not exist (there are: "
                         f"{', '.join(sorted(_benchmarks()))}):\n" + "\n".join(missing))
