import argparse

import pytest

from mapex.config import ConfigError, ExplorationConfig, apply_overrides
from mapex.prediction.config import (
    InferenceConfig,
    PredictorTrainingConfig,
    add_inference_arguments,
    inference_from_args,
)


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
