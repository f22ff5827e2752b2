"""The standard Zenoh flags of every service, turned into a `zenoh.Config`, and session opening.

With no flags every process is a peer on an ephemeral loopback port that connects to the
well-known hub endpoint (`ServicesConfig.hub_endpoint`, tcp/127.0.0.1:7447), which
`python -m services.up` serves: no router, no multicast, loopback only. `--mode`,
`--connect`, `--listen` and `--config FILE` change that. The topology and its rules:
docs/design.md#zenoh-sessions. Never fork after opening a session: spawn processes instead.
"""

from __future__ import annotations

import argparse
import json
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import zenoh

from mapex.io_limits import read_text
from services.codec import DEFAULT_SERVICES
from services.config import ServicesConfig

ZenohMode = Literal["peer", "client", "router"]
MODES = ("peer", "client", "router")

_JSON5_MESSAGE = re.compile(r'msg: "((?:[^"\\]|\\.)*)"')
_RUST_LOCATION = re.compile(r"\s+at\s+\S+\.rs:\d+\.?")


class ZenohConfigError(ValueError):
    """Zenoh flags, a config file or endpoints that Zenoh rejects; the message is one line."""


SERVICE_HELP = {
    "connect": "endpoint to connect to, repeatable (default: the loopback hub tcp/127.0.0.1:7447)",
    "listen": "endpoint to listen on, repeatable (default: tcp/127.0.0.1:0, any loopback port)",
}
HUB_HELP = {  # services.up and services.evaluate serve the hub unless told to join one
    "connect": "join the hub/router there (and its workers) instead of serving "
    "tcp/127.0.0.1:7447; every child connects there too",
    "listen": "serve the hub on this endpoint instead (the children connect to it)",
}


def add_zenoh_arguments(
    parser: argparse.ArgumentParser, help_text: dict[str, str] = SERVICE_HELP
) -> None:
    """Add --mode, --connect, --listen and --config (as in the zenoh-python examples)."""
    group = parser.add_argument_group("zenoh")
    group.add_argument(
        "--mode", choices=MODES, default=None, help="Zenoh session mode (default: peer)"
    )
    group.add_argument(
        "--connect",
        metavar="ENDPOINT",
        action="append",
        default=None,
        help=help_text["connect"],
    )
    group.add_argument(
        "--listen",
        metavar="ENDPOINT",
        action="append",
        default=None,
        help=help_text["listen"],
    )
    group.add_argument(
        "--config", metavar="FILE", default=None, help="Zenoh json5 config file (base config)"
    )


def zenoh_config_from_args(
    args: argparse.Namespace, services: ServicesConfig = DEFAULT_SERVICES
) -> zenoh.Config:
    """`zenoh_config` from the flags `add_zenoh_arguments` parsed."""
    return zenoh_config(args.mode, args.connect, args.listen, args.config, services)


def zenoh_config(
    mode: ZenohMode | None = None,
    connect: Sequence[str] | None = None,
    listen: Sequence[str] | None = None,
    config_file: str | Path | None = None,
    services: ServicesConfig = DEFAULT_SERVICES,
) -> zenoh.Config:
    """A Zenoh config: the file (when given) or the loopback defaults, then the flags given.

    None means "not given". Raises ZenohConfigError for a bad mode, a missing or invalid
    file, or a malformed endpoint.
    """
    if mode is not None and mode not in MODES:
        raise ZenohConfigError(f"Zenoh mode {mode!r} is not one of {', '.join(MODES)}")
    if config_file is not None:
        config = _config_from_file(Path(config_file))
    else:
        config = _default_config(services)
        mode = mode or "peer"
        listen = _default_listen(mode, services) if listen is None else listen
        connect = _default_connect(listen, services) if connect is None else connect
    if mode is not None:
        _insert(config, "mode", mode, "--mode")
    if listen is not None:
        _insert(config, "listen/endpoints", list(listen), "--listen endpoint")
    if connect is not None:
        _insert(config, "connect/endpoints", list(connect), "--connect endpoint")
    return config


@dataclass(frozen=True)
class FileEndpoints:
    """What a Zenoh config file says of its session's place: its `mode` (None: not named,
    Zenoh's default peer) and its connect and listen endpoints, each for the mode the
    session will have (a file may give them per mode, `{peer: [...], client: [...]}`)."""

    mode: ZenohMode | None
    connect: list[str]
    listen: list[str] | None  # None: not named (Zenoh's defaults)


def config_file_endpoints(path: str | Path, mode: ZenohMode | None = None) -> FileEndpoints:
    """The mode and endpoints of the Zenoh config file at `path`; the endpoints as a session
    in `mode` (default: the file's, else peer) would take them. ZenohConfigError (one line)
    for a missing or invalid file."""
    config = _config_from_file(Path(path))
    named = json.loads(config.get_json("mode"))
    mode = mode or named or "peer"
    listen = config.get_json("listen/endpoints")
    default_listen = zenoh.Config().get_json("listen/endpoints")
    return FileEndpoints(
        named,
        _for_mode(json.loads(config.get_json("connect/endpoints")), mode),
        None if listen == default_listen else _for_mode(json.loads(listen), mode),
    )


def _for_mode(endpoints: list[str] | dict[str, list[str]], mode: ZenohMode) -> list[str]:
    return list(endpoints.get(mode, [])) if isinstance(endpoints, dict) else list(endpoints)


def open_session(config: zenoh.Config) -> zenoh.Session:
    """Open a Zenoh session; ZenohConfigError (one line) when Zenoh refuses the config."""
    try:
        return zenoh.open(config)
    except zenoh.ZError as error:
        endpoints = (
            f"listen {config.get_json('listen/endpoints')}, "
            f"connect {config.get_json('connect/endpoints')}"
        )
        raise ZenohConfigError(
            f"cannot open a Zenoh session ({endpoints}): {_one_line(error)}"
        ) from None


def _default_config(services: ServicesConfig) -> zenoh.Config:
    """No multicast scouting; single-hop gossip so peers that meet at the hub link up."""
    config = zenoh.Config()
    _insert(config, "scouting/multicast/enabled", False, "default")
    _insert(config, "scouting/gossip/enabled", True, "default")
    _insert(config, "scouting/gossip/multihop", False, "default")
    return config


def _default_listen(mode: ZenohMode, services: ServicesConfig) -> list[str]:
    """Peers listen on any free loopback port, a router serves the hub, clients never listen."""
    return {
        "peer": [services.ephemeral_listen_endpoint],
        "router": [services.hub_endpoint],
        "client": [],
    }[mode]


def _default_connect(listen: Sequence[str], services: ServicesConfig) -> list[str]:
    """Connect to the hub, unless this session is the hub itself."""
    return [] if services.hub_endpoint in listen else [services.hub_endpoint]


def _config_from_file(path: Path) -> zenoh.Config:
    if not path.is_file():
        raise ZenohConfigError(f"Zenoh config file {path} does not exist")
    try:
        text = read_text(path)  # a regular file within the size limit
    except OSError as error:
        raise ZenohConfigError(f"Zenoh config file {path}: {error}") from None
    try:
        return zenoh.Config.from_json5(text)
    except zenoh.ZError as error:
        raise ZenohConfigError(f"Zenoh config file {path} is invalid: {_one_line(error)}") from None


def _insert(config: zenoh.Config, key: str, value: object, what: str) -> None:
    try:
        config.insert_json5(key, json.dumps(value))
    except zenoh.ZError as error:
        raise ZenohConfigError(f"bad {what} {value!r}: {_one_line(error)}") from None


def _one_line(error: Exception) -> str:
    """Zenoh's error text without its Rust source locations, wrappers and line breaks."""
    text = str(error)
    wrapped = _JSON5_MESSAGE.search(text)
    if wrapped:
        text = wrapped.group(1)
    return " ".join(_RUST_LOCATION.sub("", text).split())
