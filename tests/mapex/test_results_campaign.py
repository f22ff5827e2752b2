"""campaign.json, an experiment's episodes and settings in its results folder: written once
by whichever shard comes first, checked by the others, another campaign's refused."""

from __future__ import annotations

import json
import os
import threading

import pytest

from mapex.results import (
    CAMPAIGN_FILE,
    CampaignError,
    campaign_difference,
    campaign_record,
    claim_campaign,
    read_campaign,
)

EPISODES = {"w-nearest-start0-seed0": 60, "w-nearest-start1-seed0": 60, "w-mapex-start0-seed0": 60}
CONFIG = {"steps": 60, "seed": 0, "motion": {"cells_per_step": 1}}


def record(shards: int = 3, episodes: dict | None = None, config: dict | None = None) -> dict:
    return campaign_record(episodes or EPISODES, config or CONFIG, shards)


def test_the_first_claim_writes_it_and_the_same_campaign_is_accepted(tmp_path):
    claim_campaign(tmp_path, record())
    assert read_campaign(tmp_path) == record() and "steps" not in record()["config"]
    claim_campaign(tmp_path, record())  # another shard of the same campaign
    assert [p.name for p in tmp_path.iterdir()] == [CAMPAIGN_FILE]  # no temporary left


@pytest.mark.parametrize(
    ("mine", "problem"),
    [
        (record(shards=2), "split into 3 shard(s), not 2"),
        (record(episodes={**EPISODES, "w-mapex-start0-seed0": 80}), "for 60 steps, not 80"),
        (record(episodes={**EPISODES, "w-upen-start0-seed0": 60}), "no episode w-upen-start0"),
        (record(episodes=dict(list(EPISODES.items())[:2])), "also has episode w-mapex"),
        (record(episodes=dict(reversed(EPISODES.items()))), "in another order"),
        (
            record(config={**CONFIG, "motion": {"cells_per_step": 2}}),
            "another motion.cells_per_step (1, not 2)",
        ),
    ],
)
def test_a_shard_of_another_campaign_is_refused_in_one_line(tmp_path, mine, problem):
    claim_campaign(tmp_path, record())
    assert campaign_difference(record(), mine) is not None
    with pytest.raises(CampaignError) as raised:
        claim_campaign(tmp_path, mine)
    assert problem in str(raised.value) and "another --out" in str(raised.value)
    assert "\n" not in str(raised.value)
    assert read_campaign(tmp_path) == record()  # left as it was
    assert [p.name for p in tmp_path.iterdir()] == [CAMPAIGN_FILE]


def test_an_unsharded_run_replaces_an_unsharded_campaign_but_not_a_sharded_one(tmp_path):
    claim_campaign(tmp_path, record(shards=1))
    changed = record(shards=1, episodes={"w-upen-start0-seed0": 60})
    claim_campaign(tmp_path, changed)  # a changed experiment resumed, as before shards
    assert read_campaign(tmp_path) == changed
    with pytest.raises(CampaignError, match="split into 1 shard"):
        claim_campaign(tmp_path, record(shards=3))
    (tmp_path / CAMPAIGN_FILE).unlink()
    claim_campaign(tmp_path, record(shards=3))
    with pytest.raises(CampaignError, match="split into 3 shard"):
        claim_campaign(tmp_path, record(shards=1))  # an unsharded run into shards' folder


@pytest.mark.parametrize("text", ["{", "[]", '{"episodes": []}', '{"episodes": {}}'])
def test_an_unreadable_campaign_is_refused_in_one_line(tmp_path, text):
    (tmp_path / CAMPAIGN_FILE).write_text(text)
    with pytest.raises(CampaignError, match=CAMPAIGN_FILE):
        read_campaign(tmp_path)
    for shards in (1, 3):
        with pytest.raises(CampaignError, match="delete it once") as raised:
            claim_campaign(tmp_path, record(shards=shards))
        assert "\n" not in str(raised.value)
    assert (tmp_path / CAMPAIGN_FILE).read_text() == text


def test_shards_claiming_at_once_leave_one_campaign_and_refuse_the_other(tmp_path):
    mine, theirs = record(), record(config={**CONFIG, "seed": 1})
    outcomes: list[str] = []
    barrier = threading.Barrier(8)

    def claim(which: dict) -> None:
        barrier.wait()
        try:
            claim_campaign(tmp_path, which)
            outcomes.append("ok" if which is mine else "ok-other")
        except CampaignError:
            outcomes.append("refused")

    threads = [threading.Thread(target=claim, args=(mine if i % 2 else theirs,)) for i in range(8)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    winner = read_campaign(tmp_path)
    assert winner in (mine, theirs)
    accepted = "ok" if winner == mine else "ok-other"
    assert sorted(outcomes) == sorted([accepted] * 4 + ["refused"] * 4)
    assert [p.name for p in tmp_path.iterdir()] == [CAMPAIGN_FILE]


def test_without_hard_links_the_file_is_created_exclusively(tmp_path, monkeypatch):
    def no_links(*_args):
        raise PermissionError("hard links not supported")

    monkeypatch.setattr(os, "link", no_links)
    claim_campaign(tmp_path, record())
    claim_campaign(tmp_path, record())
    with pytest.raises(CampaignError):
        claim_campaign(tmp_path, record(shards=2))
    assert json.loads((tmp_path / CAMPAIGN_FILE).read_text()) == record()
