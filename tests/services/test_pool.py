"""The local deployment's shape: member lists, worker specs and the hub choice."""

from __future__ import annotations

import argparse

import pytest
from service_processes import free_loopback_port

from mapex.prediction.config import InferenceConfig
from services.config import ServicesConfig
from services.pool import adopt_config_file, hub_session_config, parse_member_list, worker_specs
from services.zenoh_config import ZenohConfigError


def zenoh_args(**flags) -> argparse.Namespace:
    values = {"mode": None, "connect": None, "listen": None, "config": None}
    return argparse.Namespace(**{**values, **flags})


def test_member_lists_are_checked():
    assert parse_member_list("g,g2") == ("g", "g2")
    assert parse_member_list("none") == ()
    with pytest.raises(argparse.ArgumentTypeError, match="g7"):
        parse_member_list("g,g7")


def test_worker_specs_name_replicas_and_restart_them():
    specs = worker_specs(("g", "g1"), 2, 1, ["--connect", "tcp/127.0.0.1:1"])
    assert [s.name for s in specs] == ["predictor-g-0", "predictor-g-1", "predictor-g1-0",
                                       "predictor-g1-1"]  # fmt: skip
    assert all(s.restart and s.args[-2:] == ("--connect", "tcp/127.0.0.1:1") for s in specs)
    assert [s.name for s in worker_specs(("g",), 1, 1, [])] == ["predictor-g"]


def test_worker_specs_pass_threads_and_the_inference_configuration():
    inference = InferenceConfig("bfloat16", "plain", 1)
    (spec,) = worker_specs(("g1",), 1, 3, [], inference, id_prefix="up7")
    assert spec.args == ("--member", "g1", "--worker-id", "up7-g1-0", "--threads", "3",
                         "--precision", "bfloat16", "--inference", "plain",
                         "--views", "1")  # fmt: skip
    assert (spec.member, spec.worker_id) == ("g1", "up7-g1-0")
    (default,) = worker_specs(("g",), 1, 1, [])
    assert default.args[-6:] == ("--precision", "float32", "--inference", "fused", "--views", "2")


def test_worker_specs_hand_every_worker_the_run_s_settings_before_the_zenoh_flags():
    settings = ["services.predict_timeout_s=20.0", "motion.cells_per_step=2"]
    specs = worker_specs(("g", "g2"), 1, 1, ["--connect", "tcp/127.0.0.1:1"], settings=settings)
    for spec in specs:
        assert spec.args[-6:] == (
            "--set", "services.predict_timeout_s=20.0", "--set", "motion.cells_per_step=2",
            "--connect", "tcp/127.0.0.1:1",
        )  # fmt: skip
    (plain,) = worker_specs(("g",), 1, 1, [])
    assert "--set" not in plain.args


def test_a_given_hub_is_joined_and_passed_to_every_child():
    config, flags = hub_session_config(
        zenoh_args(mode="client", connect=["tcp/10.0.0.5:7447"]), ServicesConfig()
    )
    assert flags == ["--mode", "client", "--connect", "tcp/10.0.0.5:7447"]
    assert "10.0.0.5" in config.get_json("connect/endpoints")


def test_a_listen_endpoint_makes_up_the_hub_there_a_router_with_client_children():
    config, flags = hub_session_config(zenoh_args(listen=["tcp/127.0.0.1:7999"]), ServicesConfig())
    assert flags == ["--mode", "client", "--connect", "tcp/127.0.0.1:7999"]
    assert "7999" in config.get_json("listen/endpoints")
    assert config.get_json("connect/endpoints") == "[]"
    assert config.get_json("mode") == '"router"'


def test_peer_mode_can_still_be_asked_for():
    config, flags = hub_session_config(
        zenoh_args(mode="peer", listen=["tcp/127.0.0.1:7999"]), ServicesConfig()
    )
    assert flags == ["--mode", "peer", "--connect", "tcp/127.0.0.1:7999"]
    assert config.get_json("mode") == '"peer"'


def _file(tmp_path, text: str) -> str:
    path = tmp_path / f"zenoh-{abs(hash(text))}.json5"
    path.write_text(text)
    return str(path)


def test_a_config_file_s_mode_and_endpoints_count_as_the_flags_left_out(tmp_path):
    """`services.up --config FILE` (issue #64, item 8: it served its own hub on the default
    endpoint whatever the file said): a client file's connect endpoints are joined as
    `--mode client --connect` joins them; a router file's listen endpoints are served;
    flags given win over the file."""
    hub = f"tcp/127.0.0.1:{free_loopback_port()}"  # the default hub: never claimed here
    services = ServicesConfig(hub_endpoint=hub)
    client = _file(tmp_path, '{ mode: "client", connect: { endpoints: ["tcp/10.0.0.5:7447"] } }')
    args = zenoh_args(config=client)
    assert adopt_config_file(args) == client
    assert (args.mode, args.connect, args.listen) == ("client", ["tcp/10.0.0.5:7447"], None)
    config, flags = hub_session_config(zenoh_args(config=client), services)
    assert flags == ["--config", client, "--mode", "client", "--connect", "tcp/10.0.0.5:7447"]
    assert config.get_json("mode") == '"client"' and "10.0.0.5" in config.get_json("connect")
    _, flags = hub_session_config(zenoh_args(config=client, mode="peer"), services)
    assert flags == ["--config", client, "--mode", "peer", "--connect", "tcp/10.0.0.5:7447"]
    _, flags = hub_session_config(zenoh_args(config=client, connect=["tcp/10.0.0.6:1"]), services)
    assert flags == ["--config", client, "--connect", "tcp/10.0.0.6:1"]
    per_mode = _file(tmp_path, '{ connect: { endpoints: { peer: ["tcp/10.0.0.7:1"] } } }')
    _, flags = hub_session_config(zenoh_args(config=per_mode), services)
    assert flags == ["--config", per_mode, "--connect", "tcp/10.0.0.7:1"]
    listen = f"tcp/127.0.0.1:{free_loopback_port()}"
    router = _file(tmp_path, f'{{ mode: "router", listen: {{ endpoints: ["{listen}"] }} }}')
    args = zenoh_args(config=router)
    assert adopt_config_file(args) is None and (args.mode, args.listen) == ("router", [listen])
    config, flags = hub_session_config(zenoh_args(config=router), services)
    assert flags == ["--config", router, "--mode", "client", "--connect", listen]
    assert listen in config.get_json("listen/endpoints") and hub not in config.get_json("listen")
    settings_only = _file(tmp_path, "{ scouting: { multicast: { enabled: false } } }")
    _, flags = hub_session_config(zenoh_args(config=settings_only), services)
    assert flags == ["--config", settings_only, "--mode", "client", "--connect", hub]


@pytest.mark.parametrize(
    ("text", "flags", "message"),
    [
        ('{ mode: "client" }', {}, "is in client mode but names no connect endpoint"),
        ("{}", {"mode": "client"}, "is in client mode but names no connect endpoint"),
        (
            '{ mode: "router", connect: { endpoints: ["tcp/10.0.0.5:7447"] } }',
            {},
            "is a router that connects to tcp/10.0.0.5:7447: give it mode client",
        ),
        ("{ mode: ", {}, "is invalid"),
    ],
)
def test_a_config_file_that_neither_joins_nor_serves_is_one_line(tmp_path, text, flags, message):
    path = _file(tmp_path, text)
    with pytest.raises(ZenohConfigError) as refused:
        hub_session_config(zenoh_args(config=path, **flags), ServicesConfig())
    assert message in str(refused.value) and "\n" not in str(refused.value)
