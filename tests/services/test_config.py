"""services.config.RunConfig: one run's settings, built once from `--set` items and handed to
every process of the run as the items that rebuild it (no process is started here)."""

from __future__ import annotations

import dataclasses

import pytest

from mapex.config import ConfigError, ExplorationConfig, MotionConfig
from services import planner, predictor, world
from services.config import RunConfig, ServicesConfig


def rebuilt(config: RunConfig) -> RunConfig:
    """What a child process rebuilds from the items `config` is handed on as."""
    return RunConfig().with_overrides(config.as_overrides())


def test_services_items_go_to_the_services_section_the_others_to_the_exploration():
    config = RunConfig().with_overrides(
        ["services.predict_timeout_s=20", "motion.cells_per_step=2", "steps=40"]
    )
    assert config.services == ServicesConfig(predict_timeout_s=20.0)
    assert config.services.predict_timeout_s == 20.0
    assert config.exploration == ExplorationConfig(steps=40, motion=MotionConfig(2))
    assert RunConfig() == RunConfig(ExplorationConfig(), ServicesConfig())  # nothing shared


def test_items_apply_in_order_on_top_of_the_base_without_changing_it():
    base = RunConfig(ExplorationConfig(steps=40, until_iou=0.5))
    config = base.with_overrides(["steps=60", "services.step_retries=5", "steps=70"])
    assert (config.exploration.steps, config.exploration.until_iou) == (70, 0.5)
    assert config.services.step_retries == 5
    assert base.exploration.steps == 40 and base.services == ServicesConfig()
    assert base.with_overrides([]) == base


@pytest.mark.parametrize(
    "item, message",
    [
        ("sensor.nope=1", "override 'sensor.nope=1': unknown field 'nope' (known: n_rays, "),
        ("services.nope=1", "override 'services.nope=1': unknown field 'nope' (known: "),
        ("nope=1", "override 'nope=1': unknown field 'nope' (known: "),
        ("exploration.steps=5", "unknown field 'exploration'"),  # no section named so
        ("services.predict_timeout_s=soon", "'soon' is not a valid float"),
        ("services.step_retry_pause_s=0.1,x", "'x' is not a valid float"),
        ("motion.cells_per_step=2.5", "'2.5' is not a valid int"),
        ("visibility.stop_rule=sometimes", "choose one of"),
        ("motion.cells_per_step", "'motion.cells_per_step' is not of the form"),
        ("services.hub_endpoint", "'services.hub_endpoint' is not of the form"),
        ("steps=0", "steps must be at least 1"),
        ("until_iou=2", "until_iou must be in (0, 1]"),
    ],
)
def test_a_bad_item_is_a_one_line_error_naming_it_as_given(item, message):
    with pytest.raises(ConfigError) as info:
        RunConfig().with_overrides(["steps=40", item])
    text = str(info.value)
    assert message in text and "\n" not in text
    assert "exploration." not in text.replace(f"'{item}'", "")  # the inner path stays inside


def test_the_defaults_are_handed_on_as_no_items():
    assert RunConfig().as_overrides() == []
    assert RunConfig(ExplorationConfig(until_iou=None)).as_overrides() == []  # None: default
    assert RunConfig().describe() == "settings: the defaults"


SETTINGS = [
    "motion.cells_per_step=2",  # int
    "sensor.n_rays=1000",
    "until_iou=0.3",  # an optional float, set
    "visibility.epsilon=0.65",  # float
    "visibility.stop_rule=accumulate",  # a Literal string
    "path_gain.cost_measure=cells",
    "frontier.small_clusters_last=false",  # bool
    "metrics.snapshot_steps=100,300",  # tuple of ints
    "metrics.reach_levels=0.5,0.75,0.99",  # tuple of floats
    "services.predict_timeout_s=20",  # services: float
    "services.step_retries=5",  # int
    "services.step_retry_pause_s=0.1,1.5",  # tuple of floats
    "services.hub_endpoint=tcp/127.0.0.1:7999",  # string
    "services.team_step_wait_s=0.5",
]


def test_as_overrides_round_trips_every_kind_of_setting():
    config = RunConfig().with_overrides(SETTINGS)
    items = config.as_overrides()
    assert rebuilt(config) == config
    assert len(items) == len(SETTINGS)  # one item per changed field, nothing else
    assert "services.predict_timeout_s=20.0" in items
    assert "metrics.snapshot_steps=100,300" in items
    assert "services.step_retry_pause_s=0.1,1.5" in items
    assert "frontier.small_clusters_last=False" in items
    assert "until_iou=0.3" in items and "services.hub_endpoint=tcp/127.0.0.1:7999" in items
    assert items == sorted(items, key=lambda item: item.startswith("services."))
    assert rebuilt(rebuilt(config)) == config and rebuilt(config).as_overrides() == items


def test_as_overrides_round_trips_values_set_in_code():
    """Floats that print long, a None until_iou, a field set to its default value."""
    exploration = dataclasses.replace(
        ExplorationConfig(until_iou=None, steps=7),
        visibility=dataclasses.replace(ExplorationConfig().visibility, epsilon=0.1 + 0.2),
    )
    services = ServicesConfig(predict_timeout_s=1e-3, team_step_wait_s=1 / 3, step_retries=3)
    config = RunConfig(exploration, services)
    assert rebuilt(config) == config
    assert config.as_overrides() == [
        "steps=7", "visibility.epsilon=0.30000000000000004",
        "services.predict_timeout_s=0.001", "services.team_step_wait_s=0.3333333333333333",
    ]  # fmt: skip


def test_describe_is_one_line_of_the_changed_settings():
    config = RunConfig().with_overrides(
        ["motion.cells_per_step=2", "services.predict_timeout_s=20"]
    )
    assert config.describe() == (
        "settings: motion.cells_per_step=2 services.predict_timeout_s=20.0"
    )


@pytest.mark.parametrize(
    "module, required",
    [
        (world, ["--run", "x"]),
        (planner, ["--run", "x"]),
        (predictor, ["--member", "g"]),
    ],
    ids=["world", "planner", "predictor"],
)
def test_every_child_takes_the_items_on_its_command_line(module, required):
    config = RunConfig().with_overrides(SETTINGS)
    sets = [flag for item in config.as_overrides() for flag in ("--set", item)]
    args = module.build_parser().parse_args([*required, *sets])
    assert RunConfig().with_overrides(args.overrides) == config
