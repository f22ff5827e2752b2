import argparse
import dataclasses
import importlib
import math
import typing

import pytest

from mapex.config import (
    MAX_SEED,
    RANGE,
    Checked,
    ConfigError,
    ExplorationConfig,
    Range,
    TeamConfig,
    apply_overrides,
    parse_seed,
)
from mapex.prediction.config import (
    InferenceConfig,
    PredictorTrainingConfig,
    add_inference_arguments,
    inference_from_args,
)
from mapex.worlds.config import ProceduralConfig


def test_override_sets_typed_values():
    config = apply_overrides(
        ExplorationConfig(),
        [
            "steps=12",
            "visibility.stop_rule=accumulate",
            "visibility.epsilon=0.6",
            "motion.cells_per_step=2",
        ],
    )
    assert config.steps == 12
    assert config.visibility.stop_rule == "accumulate"
    assert config.visibility.epsilon == pytest.approx(0.6)
    assert config.motion.cells_per_step == 2
    assert ExplorationConfig().visibility.stop_rule == "threshold"  # the default is untouched


def test_tuple_overrides_are_comma_separated_typed_values():
    config = apply_overrides(
        PredictorTrainingConfig(),
        ["snapshot_methods=nearest, mapex", "calibration_thresholds=0.3,0.45"],
    )
    assert config.snapshot_methods == ("nearest", "mapex")
    assert config.calibration_thresholds == (0.3, 0.45)
    with pytest.raises(ConfigError, match="not a valid float"):
        apply_overrides(config, ["calibration_thresholds=0.3,low"])


@pytest.mark.parametrize(
    "override, message",
    [
        ("nosuch=1", "unknown field 'nosuch'"),
        ("visibility.nosuch=1", "unknown field 'nosuch'"),
        ("steps=many", "not a valid int"),
        ("visibility.stop_rule=sometimes", "choose one of"),
        ("steps", "section.field=value"),
        ("team.prediction_epoch_steps=0", "must be >= 1"),
    ],
)
def test_bad_overrides_are_one_line_errors(override, message):
    with pytest.raises(ConfigError, match=message) as info:
        apply_overrides(ExplorationConfig(), [override])
    assert "\n" not in str(info.value)


def test_precision_flag_defaults_to_float32_and_refuses_others(capsys):
    parser = argparse.ArgumentParser()
    add_inference_arguments(parser)
    assert parser.parse_args([]).precision == "float32"
    assert parser.parse_args(["--precision", "bfloat16"]).precision == "bfloat16"
    with pytest.raises(SystemExit):
        parser.parse_args(["--precision", "float16"])
    assert "invalid choice: 'float16'" in capsys.readouterr().err


@pytest.mark.parametrize(
    "config",
    [InferenceConfig(), InferenceConfig("bfloat16", "plain", 1), InferenceConfig(views=1)],
    ids=str,
)
def test_inference_flags_give_back_the_configuration_a_worker_is_spawned_with(config):
    parser = argparse.ArgumentParser()
    add_inference_arguments(parser)
    assert inference_from_args(parser.parse_args([])) == InferenceConfig()
    assert inference_from_args(parser.parse_args(list(config.flags()))) == config


def test_inference_defaults_to_the_fused_path_with_two_views_in_float32():
    assert InferenceConfig() == InferenceConfig("float32", "fused", 2)


# Every field of every configuration dataclass is checked when one is built (issue #53,
# defect 9): a value of the wrong type or outside the field's declared range is a one-line
# ConfigError naming the field, so a bad `--set` stops a command before any work.

CHECKED_MODULES = (
    "mapex.config",
    "mapex.prediction.config",
    "mapex.report.config",
    "mapex.worlds.config",
    "services.config",
)


def _config_classes() -> list[type]:
    classes = []
    for name in CHECKED_MODULES:
        module = importlib.import_module(name)
        classes += [
            value
            for value in vars(module).values()
            if isinstance(value, type)
            and dataclasses.is_dataclass(value)
            and value.__module__ == name
            and issubclass(value, Checked)
        ]
    return classes


CONFIG_CLASSES = _config_classes()


def _hint(cls: type, name: str):
    return typing.get_type_hints(cls)[name]


FIELDS = [
    (cls, each, _hint(cls, each.name)) for cls in CONFIG_CLASSES for each in dataclasses.fields(cls)
]
FIELD_IDS = [f"{cls.__name__}.{each.name}" for cls, each, _ in FIELDS]


def _is_numeric(hint) -> bool:
    args = typing.get_args(hint)
    if typing.get_origin(hint) is tuple:
        return any(_is_numeric(arg) for arg in args if arg is not Ellipsis)
    if args:  # X | None
        return any(_is_numeric(arg) for arg in args)
    return hint in (int, float)


def test_every_config_dataclass_is_checked():
    names = {cls.__name__ for cls in CONFIG_CLASSES}
    expected = {
        "SensorConfig", "MotionConfig", "FrontierConfig", "NavigationConfig", "VisibilityConfig",
        "IgHectorConfig", "PipeConfig", "PathGainConfig", "UpenConfig", "MetricsConfig",
        "WorldConfig", "TeamConfig", "ExplorationConfig", "NetworkConfig",
        "PredictorTrainingConfig", "PredictorEvaluationConfig", "InpaintMemberConfig",
        "ClassicalPredictorConfig", "InferenceConfig", "ReportConfig", "ProceduralConfig",
        "HouseExpoConfig", "ServicesConfig", "WatchConfig", "Ros2Config", "WebConfig",
        "RunConfig",
    }  # fmt: skip
    assert expected <= names


@pytest.mark.parametrize("cls", CONFIG_CLASSES, ids=lambda cls: cls.__name__)
def test_every_numeric_field_declares_its_range(cls):
    unranged = [
        each.name
        for each in dataclasses.fields(cls)
        if _is_numeric(_hint(cls, each.name)) and RANGE not in each.metadata
    ]
    assert not unranged, f"{cls.__name__}: fields without a range: {unranged}"


def _wrong_type(hint):
    """A value of the wrong type for `hint`."""
    if hint is str:
        return 7
    if hint is bool:
        return "yes"
    origin = typing.get_origin(hint)
    if origin is tuple:
        return 7
    if dataclasses.is_dataclass(hint):
        return "a section"
    return "many"  # numbers, literals, X | None, tuples of those


def _out_of_range(bounds: Range):
    if bounds.low is not None:
        return bounds.low if bounds.low_open else bounds.low - 1
    return bounds.high + 1


def _with_value(each: dataclasses.Field, hint, value):
    """`value` shaped for the field: a tuple field gets it as one item of a tuple."""
    if typing.get_origin(hint) is tuple:
        default = each.default
        if isinstance(default, tuple) and default:
            if typing.get_args(hint)[-1] is Ellipsis:
                return (*default[1:], value)
            numeric = [i for i, arg in enumerate(typing.get_args(hint)) if _is_numeric(arg)]
            items = list(default)
            items[numeric[0]] = value
            return tuple(items)
        return (value,)
    return value


def _one_line_config_error(cls, name, value) -> str:
    with pytest.raises(ConfigError) as caught:
        cls(**{name: value})
    message = str(caught.value)
    assert "\n" not in message
    assert name in message
    return message


@pytest.mark.parametrize(("cls", "each", "hint"), FIELDS, ids=FIELD_IDS)
def test_a_field_of_the_wrong_type_is_a_one_line_error(cls, each, hint):
    _one_line_config_error(cls, each.name, _wrong_type(hint))


@pytest.mark.parametrize(
    ("cls", "each", "hint"),
    [(cls, each, hint) for cls, each, hint in FIELDS if RANGE in each.metadata],
    ids=[i for i, (_, each, _) in zip(FIELD_IDS, FIELDS, strict=True) if RANGE in each.metadata],
)
def test_a_field_out_of_its_range_is_a_one_line_error(cls, each, hint):
    bounds = each.metadata[RANGE]
    message = _one_line_config_error(cls, each.name, _with_value(each, hint, _out_of_range(bounds)))
    assert str(bounds) in message or "choose" in message  # InferenceConfig words its own
    if float in (hint, *typing.get_args(hint)) or _is_float_tuple(hint):
        _one_line_config_error(cls, each.name, _with_value(each, hint, math.nan))


def _is_float_tuple(hint) -> bool:
    return typing.get_origin(hint) is tuple and float in typing.get_args(hint)


def test_the_defaults_pass_their_own_checks():
    for cls in CONFIG_CLASSES:
        cls()  # raises if a default lies outside its range


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("sensor=1", "override 'sensor=1': a section takes no value; set its fields"),
        ("sensor.n_rays=0", "sensor.n_rays must be in [1, 100000], got 0"),
        ("motion.cells_per_step=0", "motion.cells_per_step must be in [1, 65535], got 0"),
        ("navigation.wall_cost_weight=inf", "must be a finite number"),
        ("metrics.snapshot_steps=200,-1", "metrics.snapshot_steps must be >= 0"),
        ("sensor.n_rays.x=1", "unknown field 'x'"),
    ],
)
def test_bad_values_are_one_line_errors_at_parse_time(override, message):
    with pytest.raises(ConfigError) as caught:
        apply_overrides(ExplorationConfig(), [override])
    assert message in str(caught.value) and "\n" not in str(caught.value)


def test_min_max_pairs_must_be_in_order():
    with pytest.raises(ConfigError, match=r"min_rows \(500\) must not exceed max_rows \(400\)"):
        ProceduralConfig(min_rows=500)


def test_seeds_are_non_negative_integers():
    assert parse_seed("0") == 0 and parse_seed(str(MAX_SEED)) == MAX_SEED
    for text in ("-1", str(MAX_SEED + 1), "1.5", "x"):
        with pytest.raises(ValueError) as caught:
            parse_seed(text)
        assert "\n" not in str(caught.value)


def test_a_team_above_max_robots_is_refused():
    TeamConfig().check_robots(64)
    with pytest.raises(ConfigError, match="--robots 65 is more than team.max_robots"):
        TeamConfig().check_robots(65)
    TeamConfig(max_robots=100).check_robots(100)
