"""Settings of the distributed simulator, and `RunConfig`: the one configuration of a run
(exploration + services), built once from defaults and `--set` and handed to every process
of the run as the `--set` items that rebuild it (`as_overrides`)."""

from __future__ import annotations

import argparse
import dataclasses
from dataclasses import dataclass, field
from typing import Any

from mapex.config import ConfigError, ExplorationConfig, apply_overrides


@dataclass(frozen=True)
class ServicesConfig:
    """Wire limits and Zenoh defaults of the distributed simulator (services/, docs/design.md)."""

    max_message_bytes: int = 32 * 2**20  # encoded payload cap, checked before unpacking
    max_decoded_bytes: int = 128 * 2**20  # cap on a message's decompressed array bytes
    compress_threshold_bytes: int = 4096  # arrays larger than this travel zlib-compressed
    zlib_level: int = 1  # fastest level: maps are mostly runs of one code
    hub_endpoint: str = "tcp/127.0.0.1:7447"  # well-known loopback endpoint served by services.up
    ephemeral_listen_endpoint: str = "tcp/127.0.0.1:0"  # default listener: loopback, any free port
    predict_timeout_s: float = 10.0  # per-member prediction query; a hung worker costs this once
    # maps above this are expected to miss the prediction timeout (one whole-map G prediction:
    # ~0.6 us/cell on one laptop-CPU thread, so 8 M cells ~5 s, twice that with four workers on
    # two cores): the run is marked degraded at start
    predict_max_cells: int = 8_000_000
    health_probe_every_s: float = 1.0  # planner: how often a benched worker is probed again
    health_probe_timeout_s: float = 2.0  # one health probe (answered at once by a live worker)
    health_check_every_s: float = 5.0  # services.up: how often its workers are probed
    # services.up restarts a worker stuck (busy on one prediction, or not answering probes)
    # this long
    unresponsive_after_s: float = 30.0
    supervision_poll_s: float = 0.2  # services.up / evaluate: how often children are checked
    publish_period_s: float = 0.1  # planner -> viewers: at most one batch of maps per period
    predict_retries: int = 3  # re-sends of a query that no worker was routed (no reply at all)
    predict_retry_pause_s: float = 0.2  # before the first re-send; doubles for each next one
    liveliness_query_timeout_s: float = 2.0  # planner's start-up discovery of live workers
    predictor_threads: int = 1  # torch CPU threads of one predictor worker (docs/design.md)
    predictor_drain_s: float = 3.0  # on shutdown, wait this long for the query being computed
    world_drain_s: float = 2.0  # on shutdown, wait this long for the step being answered
    step_timeout_s: float = 10.0  # one step query; a lost reply is retried with the same seq
    step_retries: int = 3  # the planner gives up on the world after this many x the timeout
    # back-off between step queries: first pause, doubling up to the second; a world that is
    # gone (a query that returns at once, unanswered) is asked again until the whole
    # step_retries x step_timeout_s is spent
    step_retry_pause_s: tuple[float, float] = (0.2, 2.0)
    # team world: a robot whose step request is this late after its first teammate's stands
    # still for that step
    team_step_wait_s: float = 10.0
    world_wait_s: float = 60.0  # planner start-up: how long to wait for the world's keys
    workers_wait_s: float = 120.0  # planner start-up: how long to wait for every member
    supervisor_max_restarts: int = 5  # a crashed server is restarted this often, then left dead
    stop_grace_s: float = 3.0  # services.up: SIGTERM, wait this long, then SIGKILL what is left
    hub_probe_timeout_s: float = 1.0  # connect probe of a hub port that a bind probe found taken


@dataclass(frozen=True)
class WatchConfig:
    """The live viewer `services.watch`: how often it renders, how big, how many GIF frames."""

    every_s: float = 1.0  # render at most this often (only when something new arrived)
    poll_s: float = 0.1  # how often the loop looks at arrivals (reaction time to "finished")
    get_timeout_s: float = 2.0  # late-joiner query; topics still unheard are re-asked this often
    inbox_depth: int = 8  # newest payloads kept per topic between polls (a bad one hides no good)
    dpi: int = 80
    panel_inches: float = 4.0  # width of one map panel
    max_gif_frames: int = 300  # at the cap every other frame is dropped (memory stays bounded)
    gif_max_side_px: int = 480  # GIF frames are downscaled to fit this square
    gif_frame_ms: int = 200


@dataclass(frozen=True)
class Ros2Config:
    """The ROS 2 bridge `services.ros2` (rmw_zenoh conventions: mapex.interop.rmw_zenoh)."""

    domain_id: int = 0  # ROS_DOMAIN_ID of the ROS 2 graph the topics appear in
    node_name: str = "mapex_bridge"  # what `ros2 node list` shows
    latched_depth: int = 1  # maps: transient local, the last one kept for late subscribers
    volatile_depth: int = 10  # pose and paths
    heartbeat_s: float = 0.5  # sample-miss heartbeat of reliable latched topics (as rmw_zenoh)
    max_runs: int = 8  # the topics of older runs are withdrawn (their tokens undeclared)
    # the whole trajectory at most this often per robot (and once more when the run ends); the
    # pose goes out every step
    trajectory_period_s: float = 1.0
    default_resolution_m: float = 0.1  # cell size until a run's world_info arrives
    # a recording goes on this long after a run's final status: Zenoh orders samples per key only,
    # so the last maps and poses may still be on their way
    settle_s: float = 0.5


@dataclass(frozen=True)
class WebConfig:
    """The browser view `services.web`: where it serves, how much it sends, what it keeps."""

    host: str = "127.0.0.1"  # loopback only unless allow_remote: the view has no authentication
    port: int = 8000  # 0: any free port, logged (8765 is the Foxglove server's)
    allow_remote: bool = False  # serve a non-loopback host and accept any Host header
    # per robot and map kind; a map held back is replaced by newer ones and sent as soon as its
    # turn comes (the newest always gets out)
    map_events_per_s: float = 4.0
    flush_poll_s: float = 0.05  # how often held-back maps are looked at
    keepalive_s: float = 5.0  # an SSE comment after this long without events (finds gone clients)
    retry_ms: int = 1000  # how long a browser waits before reconnecting a dropped stream
    # a client this far behind is dropped (it reconnects and starts again from a fresh snapshot)
    client_max_queued_events: int = 512
    max_metric_points: int = 5000  # metric samples kept per robot for late pages
    max_trajectory_points: int = 20000  # poses kept per robot for late pages
    max_runs: int = 32  # runs kept; the one updated least recently is forgotten first
    close_timeout_s: float = 5.0  # how long `WebView.close` waits for each of its threads


DEFAULT_WEB = WebConfig()


SERVICES_SECTION = "services"  # `--set services.FIELD=VALUE` reaches `RunConfig.services`


@dataclass(frozen=True)
class RunConfig:
    """Everything the processes of one run share: the exploration settings (the world's
    sensor and motion, the planners' methods and metrics) and the services section."""

    exploration: ExplorationConfig = field(default_factory=ExplorationConfig)
    services: ServicesConfig = field(default_factory=ServicesConfig)

    def with_overrides(self, overrides: list[str]) -> RunConfig:
        """This configuration with `--set` items applied: `services.FIELD=VALUE` to the
        services section, every other one to the exploration's (ConfigError, one line)."""
        config = self
        for item in overrides:
            section = item.partition(".")[0]
            path = item if section == SERVICES_SECTION else f"exploration.{item}"
            try:
                config = apply_overrides(config, [path])
            except ConfigError as error:
                raise ConfigError(str(error).replace(f"'{path}'", f"'{item}'")) from None
        return config

    def describe(self) -> str:
        """One line for the logs: the settings that differ from the defaults."""
        changed = self.as_overrides()
        return "settings: " + (" ".join(changed) if changed else "the defaults")

    def as_overrides(self) -> list[str]:
        """The `--set` items that rebuild this configuration from the defaults: how it is
        handed to every process of a run."""
        return [
            *_changed_fields(self.exploration, ExplorationConfig(), ""),
            *_changed_fields(self.services, ServicesConfig(), f"{SERVICES_SECTION}."),
        ]


def _changed_fields(config: Any, default: Any, prefix: str) -> list[str]:
    items = []
    for each in dataclasses.fields(config):
        value, base = getattr(config, each.name), getattr(default, each.name)
        if dataclasses.is_dataclass(value):
            items += _changed_fields(value, base, f"{prefix}{each.name}.")
        elif value != base:
            text = ",".join(map(str, value)) if isinstance(value, tuple) else str(value)
            items.append(f"{prefix}{each.name}={text}")
    return items


def add_run_config_argument(parser: argparse.ArgumentParser) -> None:
    """--set SECTION.FIELD=VALUE (repeatable) into `args.overrides`, for `RunConfig`."""
    parser.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="SECTION.FIELD=VALUE",
        help="override a setting of the run (repeatable): an exploration field, e.g. "
        "motion.cells_per_step=2, or a services one, e.g. services.predict_timeout_s=20",
    )
