"""Parameters of the detector node: defaults, the YAML file, validation, descriptors."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
import yaml

from signal_light_node.errors import ConfigError
from signal_light_node.ros.params import (NODE_NAME, PARAM_SPECS, DetectorParams, updated,
                                           validate_params)

YAML = Path(__file__).resolve().parent.parent / "config" / "detector.yaml"


def _yaml_params() -> dict:
    return yaml.safe_load(YAML.read_text())[NODE_NAME]["ros__parameters"]


def test_every_field_has_a_spec_in_order():
    assert [f.name for f in dataclasses.fields(DetectorParams)] == list(PARAM_SPECS)


def test_backend_choices_come_from_the_registry():
    """Not a hand-written list: a backend the registry knows is a valid parameter value."""
    from signal_light_node.model.backends.registry import known_backends
    from signal_light_node.runtime.backend import AUTO_BACKEND

    choices = PARAM_SPECS["backend"].choices
    assert choices[-1] == AUTO_BACKEND and {"torch", "onnxruntime"} <= set(choices)
    assert set(choices[:-1]) <= set(known_backends())  # a test may register more later
    assert validate_params({"backend": "onnxruntime"}).backend == "onnxruntime"
    with pytest.raises(ConfigError, match="backend must be one of"):
        validate_params({"backend": "tensorrt"})


def test_yaml_holds_exactly_the_declared_defaults():
    from_yaml = _yaml_params()
    defaults = DetectorParams().as_dict()
    assert list(from_yaml) == list(defaults)
    for name, value in defaults.items():
        # Same value and same YAML type (1 vs 1.0 decides int vs double in ROS).
        assert from_yaml[name] == value and type(from_yaml[name]) is type(value), name
    assert validate_params(from_yaml) == DetectorParams()


def test_defaults_are_valid_and_thresholds_keyed_by_code():
    params = validate_params({})
    assert params == DetectorParams()
    assert params.thresholds == {100: 0.5, 101: 0.5, 102: 0.5}


def test_int_for_float_is_accepted_and_converted():
    params = validate_params({"sync_timeout_s": 2})
    assert params.sync_timeout_s == 2.0 and isinstance(params.sync_timeout_s, float)


@pytest.mark.parametrize("changes, words", [
    ({"device": "tpu"}, ["device", "cpu, cuda", "'tpu'"]),
    ({"image_transport": "theora"}, ["image_transport", "raw, compressed"]),
    ({"reliability": "sometimes"}, ["reliability"]),
    ({"threshold_brake": 1.5}, ["threshold_brake", "<= 1.0"]),
    ({"threshold_left_blinker": float("nan")}, ["threshold_left_blinker", "NaN"]),
    ({"work_queue_size": 0}, ["work_queue_size", ">= 1"]),
    ({"max_tracks": 2.5}, ["max_tracks", "integer"]),
    ({"max_tracks": True}, ["max_tracks", "integer"]),
    ({"publish_debug_image": 1}, ["publish_debug_image", "true or false"]),
    ({"sync_slop_s": -0.1}, ["sync_slop_s", ">= 0.0"]),
    ({"sync_slop_s": 0.5, "sync_timeout_s": 0.2}, ["sync_timeout_s", "exceed sync_slop_s"]),
    ({"model_path": 3}, ["model_path", "string"]),
    ({"thresold_brake": 0.3}, ["unknown parameter 'thresold_brake'"]),
    ({"filter_hold_s": -0.5}, ["filter_hold_s", ">= 0.0"]),
    ({"filter_on_threshold": 0.0}, ["filter_on_threshold", ">= 0.01"]),
    ({"intent_filter": "yes"}, ["intent_filter", "true or false"]),
])
def test_bad_values_are_refused_with_a_reason(changes, words):
    with pytest.raises(ConfigError) as info:
        validate_params(changes)
    for word in words:
        assert word in str(info.value)


def test_every_problem_is_named_at_once():
    with pytest.raises(ConfigError) as info:
        validate_params({"device": "tpu", "max_tracks": 0})
    assert "device" in str(info.value) and "max_tracks" in str(info.value)


def test_runtime_updates_only_for_dynamic_parameters():
    params = DetectorParams()
    assert updated(params, {"sync_slop_s": 0.02}).sync_slop_s == 0.02
    assert updated(params, {"sync_timeout_s": 3}).sync_timeout_s == 3.0
    for name, value in (("model_path", "/tmp/other.pt"), ("threshold_brake", 0.7),
                        ("max_tracks", 3)):
        with pytest.raises(ConfigError, match="read-only"):
            updated(params, {name: value})
    with pytest.raises(ConfigError, match="<= 1.0"):
        updated(params, {"sync_slop_s": 2.0})
    with pytest.raises(ConfigError, match="exceed sync_slop_s"):
        updated(params, {"sync_slop_s": 0.5, "sync_timeout_s": 0.4})


def test_descriptors_on_a_real_node():
    rclpy = pytest.importorskip("rclpy")
    from rcl_interfaces.msg import ParameterType
    from rclpy.parameter import Parameter

    from signal_light_node.ros.params import read_parameters

    context = rclpy.Context()
    rclpy.init(context=context, args=["--ros-args", "-p", "threshold_brake:=0.25"])
    try:
        node = rclpy.create_node("params_probe", context=context)
        try:
            params = read_parameters(node)
            assert params.threshold_brake == 0.25 and params.device == "cpu"
            (desc,) = node.describe_parameters(["threshold_brake"])
            assert desc.type == ParameterType.PARAMETER_DOUBLE and desc.read_only
            assert desc.floating_point_range[0].to_value == 1.0
            (desc,) = node.describe_parameters(["sync_slop_s"])
            assert not desc.read_only and desc.floating_point_range[0].from_value == 0.0
            (desc,) = node.describe_parameters(["model_path"])
            assert desc.read_only and "shipped" in desc.description
            (desc,) = node.describe_parameters(["max_tracks"])
            assert desc.integer_range[0].from_value == 1
            # rclpy itself enforces the declared range and read-only flag at run time.
            result = node.set_parameters([Parameter("sync_slop_s", value=3.0)])[0]
            assert not result.successful
            result = node.set_parameters([Parameter("threshold_brake", value=0.3)])[0]
            assert not result.successful and "read-only" in result.reason.lower()
        finally:
            node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)


@pytest.mark.parametrize("args, words", [
    (["-p", "threshold_brake:=7.0"], ["threshold_brake", "<= 1.0"]),
    (["-p", "max_tracks:=2.5"], ["max_tracks"]),
    (["-p", "treshold_brake:=0.2"], ["unknown parameter", "treshold_brake"]),
])
def test_bad_values_on_a_real_node_become_config_errors(args, words):
    rclpy = pytest.importorskip("rclpy")
    from signal_light_node.ros.params import read_parameters

    context = rclpy.Context()
    rclpy.init(context=context, args=["--ros-args", *args])
    try:
        node = rclpy.create_node("params_probe", context=context)
        try:
            with pytest.raises(ConfigError) as info:
                read_parameters(node)
            for word in words:
                assert word in str(info.value)
        finally:
            node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)


def test_node_defaults_equal_the_engine_and_pairing_defaults():
    # The live node and `signal-light replay` must behave alike out of the box.
    from signal_light_node.runtime.engine import EngineConfig
    from signal_light_node.runtime.pairing import PairingConfig

    engine, params, pairing = EngineConfig(), DetectorParams(), PairingConfig()
    assert params.thresholds == dict(engine.thresholds)
    assert (params.track_timeout_s, params.max_tracks, params.max_gap_s, params.device) == (
        engine.track_timeout_s, engine.max_tracks, engine.max_gap_s, engine.device)
    assert params.intent_filter_config == engine.intent_filter
    assert (params.sync_slop_s, params.sync_timeout_s, params.image_queue_size,
            params.detection_queue_size) == (pairing.slop_s, pairing.timeout_s,
                                             pairing.max_images, pairing.max_detections)


def test_crop_margin_is_retired_an_old_value_is_warned_about_and_ignored(caplog):
    # The crop margin is the checkpoint's; an old params file that still sets it must load.
    assert "crop_margin" not in PARAM_SPECS
    old = dict(_yaml_params(), crop_margin=0.3)
    with caplog.at_level("WARNING"):
        assert validate_params(old) == DetectorParams()
    assert "crop_margin (0.3) is no longer used and is ignored" in caplog.text
    assert "checkpoint" in caplog.text


def test_crop_margin_on_a_real_node_is_one_warning_not_an_error(tmp_path):
    rclpy = pytest.importorskip("rclpy")
    from signal_light_node.ros.params import read_parameters

    old = yaml.safe_load(YAML.read_text())
    old[NODE_NAME]["ros__parameters"]["crop_margin"] = 0.25
    path = tmp_path / "old.yaml"
    path.write_text(yaml.safe_dump(old))
    context = rclpy.Context()
    rclpy.init(context=context, args=["--ros-args", "--params-file", str(path)])
    try:
        node = rclpy.create_node(NODE_NAME, context=context)
        warnings = []
        node.get_logger = lambda: type("L", (), {"warning": staticmethod(warnings.append)})()
        try:
            assert read_parameters(node) == DetectorParams()
            assert len(warnings) == 1 and "crop_margin (0.25)" in warnings[0]
            assert not node.has_parameter("crop_margin")
        finally:
            node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)
