"""The docs cannot drift from the code: the protocol page names every key and message field,
every `docs/<page>.md#anchor` a docstring cites exists, and every `python -m` command the
docs and docstrings quote answers `--help`."""

import ast
import dataclasses
import re
from functools import cache
from pathlib import Path

import pytest
from commands_at_once import helps_at_once

from services.keys import KEY_PREFIX, ROBOT_TOPICS, RUN_TOPICS
from services.messages import Message

ROOT = Path(__file__).resolve().parents[1]
PROTOCOL = (ROOT / "docs" / "protocol.md").read_text()
MESSAGES = PROTOCOL.split("\n## Messages\n", 1)[1].split("\n## ", 1)[0]  # the messages' table
SOURCES = [*ROOT.glob("mapex/**/*.py"), *ROOT.glob("services/**/*.py")]
SOURCES += ROOT.glob("deploy/**/*.py")


def _documented_keys() -> set[str]:
    return set(re.findall(r"^\| `(mapex/@v1/[^`]+)` \|", PROTOCOL, flags=re.MULTILINE))


def test_every_key_of_the_protocol_is_documented_and_no_other():
    expected = {f"{KEY_PREFIX}/<run>/<robot>/{topic}" for topic in ROBOT_TOPICS}
    expected |= {f"{KEY_PREFIX}/<run>/{topic}" for topic in RUN_TOPICS}
    expected |= {
        f"{KEY_PREFIX}/predict/<member>/<worker_id>",
        f"{KEY_PREFIX}/health/<member>/<worker_id>",
        f"{KEY_PREFIX}/alive/predict/<member>/<worker_id>",
        f"{KEY_PREFIX}/alive/world/<run>",
        f"{KEY_PREFIX}/alive/planner/<run>/<robot>",
    }
    assert _documented_keys() == expected


@pytest.mark.parametrize("message_type", sorted(Message._REGISTRY))
def test_every_message_and_field_is_documented(message_type):
    rows = re.findall(rf"^\| `{message_type}` \| (.*) \|$", MESSAGES, flags=re.MULTILINE)
    assert len(rows) == 1, f"no row for message type {message_type!r}"
    fields = [f.name for f in dataclasses.fields(Message._REGISTRY[message_type])]
    documented = re.findall(r"`([a-z_0-9]+)`", rows[0])
    assert documented == fields


def _cited_anchors() -> set[tuple[str, str]]:
    cited = set()
    for path in SOURCES:
        for page, anchor in re.findall(r"docs/([a-z_]+\.md)#([a-z0-9-]+)", path.read_text()):
            cited.add((page, anchor))
    return cited


def _anchor(title: str) -> str:
    """GitHub's anchor of a Markdown heading."""
    return re.sub(r"[^a-z0-9 -]", "", title.strip().lower()).replace(" ", "-")


def test_docstrings_cite_anchors_that_exist():
    cited = _cited_anchors()
    assert cited, "the docstrings cite docs/algorithms.md sections"
    for page, anchor in sorted(cited):
        text = (ROOT / "docs" / page).read_text()
        titles = re.findall(r"^#+ (.*)$", text, flags=re.MULTILINE)
        assert anchor in {_anchor(t) for t in titles}, f"docs/{page}#{anchor} does not exist"


def test_no_docstring_cites_the_spec_outside_the_repository():
    citing = [
        str(path.relative_to(ROOT))
        for path in [*ROOT.glob("mapex/**/*.py"), *ROOT.glob("services/**/*.py")]
        if re.search(r"SPEC §|SPEC\.md", path.read_text())
    ]
    assert citing == []


def test_every_method_is_in_the_readme_table_and_the_algorithms_page():
    from mapex.methods import METHODS

    readme = (ROOT / "README.md").read_text()
    algorithms = (ROOT / "docs" / "algorithms.md").read_text()
    for name in METHODS:
        assert f"| `{name}` |" in readme, f"{name} is missing from the README's methods table"
        assert f"`{name}`" in algorithms, f"{name} is missing from docs/algorithms.md"


# ---------------------------------------------------------------------------- quoted commands

# `python -m MODULE [SUBCOMMAND]`, with `| MODULE` alternatives as the README writes them
# (`python -m services.web | services.ros2`); only this project's packages
_MODULE = r"(?:mapex|services|deploy)(?:\.\w+)*"
_QUOTED = re.compile(
    rf"python3?\s+-m\s+({_MODULE})\b(?:[ \t]+([a-z][a-z_-]*)(?![\w/.:-]))?"
    rf"((?:[ \t]*\|[ \t]*{_MODULE}\b)*)"
)
# the exec form of deploy/compose.yaml and deploy/Dockerfile: "python", "-m", "MODULE"
_QUOTED_EXEC = re.compile(rf'"python3?",\s*"-m",\s*"({_MODULE})"(?:,\s*"([a-z][a-z_-]*)")?')
_SUBCOMMANDS = re.compile(r"^usage: .*? \{([a-z_,-]+)\}", flags=re.MULTILINE)


def _docstrings(path: Path) -> str:
    tree = ast.parse(path.read_text())
    kinds = (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)
    nodes = [node for node in ast.walk(tree) if isinstance(node, kinds)]
    return "\n".join(ast.get_docstring(node, clean=False) or "" for node in nodes)


def _quoting_texts() -> dict[str, str]:
    """Every docstring of the packages, and every page and deployment file that quotes commands."""
    texts = {str(path.relative_to(ROOT)): _docstrings(path) for path in SOURCES}
    pages = [ROOT / "README.md", *ROOT.glob("docs/**/*.md"), ROOT / "deploy" / "README.md"]
    pages += [*ROOT.glob("deploy/systemd/*"), ROOT / "deploy" / "compose.yaml"]
    pages += [*ROOT.glob("Dockerfile"), *ROOT.glob("deploy/Dockerfile")]
    texts |= {str(path.relative_to(ROOT)): path.read_text() for path in pages if path.is_file()}
    return texts


def _quoted_commands() -> dict[tuple[str, str | None], str]:
    """(module, the word after it or None) -> the first file quoting it."""
    quoted: dict[tuple[str, str | None], str] = {}
    for source, text in _quoting_texts().items():
        for match in _QUOTED.finditer(text):
            quoted.setdefault((match[1], match[2]), source)
            for module in re.findall(_MODULE, match[3] or ""):
                quoted.setdefault((module, None), source)
        for match in _QUOTED_EXEC.finditer(text):
            quoted.setdefault((match[1], match[2]), source)
    return quoted


QUOTED = _quoted_commands()
QUOTED_MODULES = sorted({module for module, _ in QUOTED})


def _answers(commands: list[tuple[str, ...]]) -> dict[tuple[str, ...], tuple[int, str]]:
    """(exit code, output) of `python -m COMMAND --help` of each command, run in parallel
    (each is mostly imports) and once per session (tests/test_imports.py asks for some too)."""
    done = helps_at_once(commands)
    return {c: (d.returncode, d.stdout + d.stderr) for c, d in zip(commands, done, strict=True)}


@cache
def _helps() -> dict[tuple[str, ...], tuple[int, str]]:
    """`python -m MODULE --help` of every quoted module, then `MODULE SUBCOMMAND --help` of every
    quoted word its usage lists as a subcommand."""
    helps = _answers([(module,) for module in QUOTED_MODULES])
    subcommands = sorted(
        (module, word)
        for module, word in QUOTED
        if word and word in _subcommands(helps[(module,)][1])
    )
    return helps | _answers(subcommands)


def _subcommands(help_text: str) -> set[str]:
    match = _SUBCOMMANDS.search(help_text)
    return set(match[1].split(",")) if match else set()


def test_the_docs_quote_the_commands_of_every_entry_point():
    assert {"mapex", "services.up", "services.evaluate", "deploy.router"} <= set(QUOTED_MODULES)
    assert ("mapex", "run") in _helps(), "python -m mapex run is quoted and has --help"


@pytest.mark.parametrize("module", QUOTED_MODULES)
def test_every_quoted_python_m_command_answers_help(module):
    for command, (returncode, output) in _helps().items():
        if command[0] != module:
            continue
        where = next(source for (quoted, _), source in QUOTED.items() if quoted == module)
        shown = f"python -m {' '.join(command)} --help (quoted in {where})"
        assert returncode == 0, f"{shown} exited {returncode}:\n{output[-2000:]}"
        assert output.strip(), f"{shown} printed nothing: no command line there"
        assert "usage:" in output, f"{shown} printed no usage:\n{output[-2000:]}"
