"""The docs cannot drift from the code: the protocol page names every key and message field,
and every `docs/algorithms.md#anchor` a docstring cites exists."""

import dataclasses
import re
from pathlib import Path

import pytest

from services.keys import KEY_PREFIX, ROBOT_TOPICS, RUN_TOPICS
from services.messages import Message

ROOT = Path(__file__).resolve().parents[1]
PROTOCOL = (ROOT / "docs" / "protocol.md").read_text()


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
    rows = re.findall(rf"^\| `{message_type}` \| (.*) \|$", PROTOCOL, flags=re.MULTILINE)
    assert len(rows) == 1, f"no row for message type {message_type!r}"
    fields = [f.name for f in dataclasses.fields(Message._REGISTRY[message_type])]
    documented = re.findall(r"`([a-z_0-9]+)`", rows[0])
    assert documented == fields


def _cited_anchors() -> set[tuple[str, str]]:
    cited = set()
    for path in [*ROOT.glob("mapex/**/*.py"), *ROOT.glob("services/*.py")]:
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
        for path in [*ROOT.glob("mapex/**/*.py"), *ROOT.glob("services/*.py")]
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
