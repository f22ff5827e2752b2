"""Settings of the distributed simulator, and `RunConfig`: the one configuration of a run
(exploration + services), built once from defaults and `--set` and handed to every process
of the run as the `--set` items that rebuild it (`as_overrides`)."""

from __future__ import annotations

import argparse
import dataclasses
from dataclasses import dataclass, field
from typing import Any

from mapex.config import (
    MAX_PROCESSES_PER_CPU,
    PROCESS_MEMORY_BYTES,
    Checked,
    ConfigError,
    ExplorationConfig,
    add_override_argument,
    apply_overrides,
    check_process_count,
    positive,
    ranged,
)

MAX_PORT = 65_535


@dataclass(frozen=True)
class ServicesConfig(Checked):
    """Wire limits and Zenoh defaults of the distributed simulator (services/, docs/design.md)."""

    SECTION = "services"
    max_message_bytes: int = ranged(32 * 2**20, 1)  # encoded payload cap, checked before unpacking
    max_decoded_bytes: int = ranged(128 * 2**20, 1)  # cap on a message's decompressed array bytes
    # msgpack objects (maps, lists, scalars) in one payload, counted before unpacking: a
    # message holds a few hundred; 31 MiB of empty maps would be 31 M Python objects (3 GB)
    max_message_objects: int = ranged(65536, 16)
    # arrays larger than this travel zlib-compressed
    compress_threshold_bytes: int = ranged(4096, 0)
    zlib_level: int = ranged(1, 0, 9)  # fastest level: maps are mostly runs of one code
    hub_endpoint: str = "tcp/127.0.0.1:7447"  # well-known loopback endpoint served by services.up
    ephemeral_listen_endpoint: str = "tcp/127.0.0.1:0"  # default listener: loopback, any free port
    # per-member prediction query; a hung worker costs this once
    predict_timeout_s: float = positive(10.0)
    # maps above this are expected to miss the prediction timeout (one whole-map G prediction:
    # ~0.6 us/cell on one laptop-CPU thread, so 8 M cells ~5 s, twice that with four workers on
    # two cores): the run is marked degraded at start
    predict_max_cells: int = ranged(8_000_000, 1)
    # planner: how often a benched worker is probed again
    health_probe_every_s: float = positive(1.0)
    # planner: a worker that failed a query (timed out, ended it unanswered, answered for
    # another worker, or implausibly) gets no query for bench_first_s, doubled for each further
    # failure before its next good answer, up to bench_max_s. Only a timely, valid answer clears
    # its record; its own health reply never does (docs/design.md#reliability)
    bench_first_s: float = positive(30.0)
    bench_max_s: float = positive(600.0)
    # ... a worker is benched at the this-many-th of its queries in a row that ended with no
    # reply at all (the first may be a route still being built, eclipse-zenoh#2767)
    bench_after_unanswered: int = ranged(2, 1)
    # planner: a member's answer that predicts occupied on more than this share of the known
    # free cells of its crop, or free on more than this share of its known walls, or one value
    # on every unknown cell, is implausible: left out (degraded) and its worker benched. The
    # shipped ensemble's raw outputs contradict at most ~12% of the known free cells (next to
    # walls) and ~14% of the known walls (noisy IPA scans) on seven development maps
    # (tests/services/test_rogue_workers.py); 1 turns the check off
    implausible_share: float = ranged(0.4, 0, 1)
    implausible_min_cells: int = ranged(32, 1)  # fewer known cells of a kind are not judged
    # planner: with at least three members answering a crop, an answer that disagrees (wall
    # or not) with the others' consensus on more than this share of the unknown cells where
    # every other member agrees is left out (degraded) and its worker benched, as
    # implausible ones are; judged from implausible_min_cells such cells. The shipped
    # members' largest share on the KTH validation snapshots is measured in
    # docs/design.md#trust; 1 turns the check off
    consensus_max_disagreement: float = ranged(0.4, 0, 1)
    # one health probe (answered at once by a live worker)
    health_probe_timeout_s: float = positive(2.0)
    health_check_every_s: float = positive(5.0)  # services.up: how often its workers are probed
    # services.up restarts a worker stuck (busy on one prediction, or not answering probes)
    # this long
    unresponsive_after_s: float = positive(30.0)
    # services.up / evaluate: how often children are checked
    supervision_poll_s: float = positive(0.2)
    # planner -> viewers: at most one batch of maps per period
    publish_period_s: float = positive(0.1)
    # re-sends of a query that no worker was routed (no reply at all)
    predict_retries: int = ranged(3, 0)
    # before the first re-send; doubles for each next one
    predict_retry_pause_s: float = positive(0.2)
    # planner's start-up discovery of live workers
    liveliness_query_timeout_s: float = positive(2.0)
    # the oracle worker: how long it asks for a run's ground truth before refusing a request of
    # that run, and how many runs' walls it keeps (a pool serves many runs at once)
    oracle_truth_wait_s: float = positive(5.0)
    oracle_runs_kept: int = ranged(8, 1)
    # torch CPU threads of one predictor worker (docs/design.md)
    predictor_threads: int = ranged(1, 1)
    # on shutdown, wait this long for the query being computed, then leave it (keep it well
    # below stop_grace_s: the worker must be gone before services.up's SIGKILL)
    predictor_drain_s: float = ranged(1.0, 0)
    world_drain_s: float = ranged(2.0, 0)  # on shutdown, wait this long for the step being answered
    # one step query; a lost reply is retried with the same seq
    step_timeout_s: float = positive(10.0)
    # the planner gives up on the world after this many x the timeout
    step_retries: int = ranged(3, 1)
    # back-off between step queries: first pause, doubling up to the second; a world that is
    # gone (a query that returns at once, unanswered) is asked again until the whole
    # step_retries x step_timeout_s is spent
    step_retry_pause_s: tuple[float, float] = positive((0.2, 2.0))
    # team world: a robot whose step request is this late after its first teammate's stands
    # still for that step
    team_step_wait_s: float = positive(10.0)
    world_wait_s: float = positive(60.0)  # planner start-up: how long to wait for the world's keys
    workers_wait_s: float = positive(120.0)  # planner start-up: how long to wait for every member
    # a crashed server is restarted this often, then left dead
    supervisor_max_restarts: int = ranged(5, 0)
    # services.up: SIGTERM, wait this long, then SIGKILL what is left
    stop_grace_s: float = ranged(3.0, 0)
    # connect probe of a hub port that a bind probe found taken, and of every --connect
    # endpoint of services.up / evaluate before any child starts
    hub_probe_timeout_s: float = positive(1.0)
    # services.up / evaluate with --connect: a run whose session has had no router for this
    # long (the hub it joined ended, or the router stopped) ends with one line
    hub_lost_grace_s: float = positive(10.0)
    # services.up / evaluate start at most this many processes (planners, worlds, workers,
    # tools) per CPU core this process may use, and no more than the memory holds at
    # process_memory_bytes each
    max_processes_per_cpu: int = ranged(MAX_PROCESSES_PER_CPU, 1)
    process_memory_bytes: int = ranged(PROCESS_MEMORY_BYTES, 1)

    def check_processes(self, count: int, what: str) -> None:
        """ConfigError (one line naming the caps) when `count` child processes, started for
        `what` (the flags that ask for them), are more than this machine holds."""
        check_process_count(
            count,
            what,
            self.max_processes_per_cpu,
            self.process_memory_bytes,
            "--set services.max_processes_per_cpu=N and services.process_memory_bytes=N",
        )


@dataclass(frozen=True)
class WatchConfig(Checked):
    """The live viewer `services.watch`: how often it renders, how big, how many GIF frames."""

    SECTION = "watch"
    every_s: float = positive(1.0)  # render at most this often (only when something new arrived)
    # how often the loop looks at arrivals (reaction time to "finished")
    poll_s: float = positive(0.1)
    # late-joiner query; topics still unheard are re-asked this often
    get_timeout_s: float = positive(2.0)
    # newest payloads kept per topic between polls (a bad one hides no good)
    inbox_depth: int = ranged(8, 1)
    dpi: int = ranged(80, 1, 2400)
    panel_inches: float = ranged(4.0, 0, 100, low_open=True)  # width of one map panel
    # at the cap every other frame is dropped (memory stays bounded)
    max_gif_frames: int = ranged(300, 2)
    gif_max_side_px: int = ranged(480, 1)  # GIF frames are downscaled to fit this square
    gif_frame_ms: int = ranged(200, 1)


@dataclass(frozen=True)
class Ros2Config(Checked):
    """The ROS 2 bridge `services.ros2` (rmw_zenoh conventions: mapex.interop.rmw_zenoh)."""

    SECTION = "ros2"
    domain_id: int = ranged(0, 0, 232)  # ROS_DOMAIN_ID of the ROS 2 graph the topics appear in
    node_name: str = "mapex_bridge"  # what `ros2 node list` shows
    # maps: transient local, the last one kept for late subscribers
    latched_depth: int = ranged(1, 1)
    volatile_depth: int = ranged(10, 1)  # pose and paths
    # sample-miss heartbeat of reliable latched topics (as rmw_zenoh)
    heartbeat_s: float = positive(0.5)
    max_runs: int = ranged(8, 1)  # the topics of older runs are withdrawn (their tokens undeclared)
    # the whole trajectory at most this often per robot (and once more when the run ends); the
    # pose goes out every step
    trajectory_period_s: float = ranged(1.0, 0)
    default_resolution_m: float = positive(0.1)  # cell size until a run's world_info arrives
    # a recording goes on this long after a run's final status: Zenoh orders samples per key only,
    # so the last maps and poses may still be on their way
    settle_s: float = ranged(0.5, 0)


@dataclass(frozen=True)
class WebConfig(Checked):
    """The browser view `services.web`: where it serves, how much it sends, what it keeps."""

    SECTION = "web"
    host: str = "127.0.0.1"  # loopback only unless allow_remote: the view has no authentication
    # 0: any free port, logged (8765 is the Foxglove server's)
    port: int = ranged(8000, 0, MAX_PORT)
    allow_remote: bool = False  # serve a non-loopback host and accept any Host header
    # per robot and map kind; a map held back is replaced by newer ones and sent as soon as its
    # turn comes (the newest always gets out)
    map_events_per_s: float = positive(4.0)
    flush_poll_s: float = positive(0.05)  # how often held-back maps are looked at
    # an SSE comment after this long without events (finds gone clients)
    keepalive_s: float = positive(5.0)
    retry_ms: int = ranged(1000, 0)  # how long a browser waits before reconnecting a dropped stream
    # a client this far behind is dropped (it reconnects and starts again from a fresh snapshot)
    client_max_queued_events: int = ranged(512, 1)
    # ... or this many bytes behind; maps never pile up: a robot's newer map of a kind
    # replaces the one still queued for a slow client (latest wins)
    client_max_queued_bytes: int = ranged(8 * 2**20, 1)
    # HTTP connections served at once (a thread each); one more is answered 503 and closed
    max_connections: int = ranged(64, 1)
    # a request's line and headers must have arrived this long after its connection was
    # accepted, else the connection is closed (a slow or partial request holds no slot long)
    request_timeout_s: float = positive(5.0)
    # a write the client has not taken after this long ends its connection (a client that
    # does not read)
    send_timeout_s: float = positive(10.0)
    max_metric_points: int = ranged(5000, 1)  # metric samples kept per robot for late pages
    max_trajectory_points: int = ranged(20000, 1)  # poses kept per robot for late pages
    max_runs: int = ranged(32, 1)  # runs kept; the one updated least recently is forgotten first
    # how long `WebView.close` waits for each of its threads
    close_timeout_s: float = ranged(5.0, 0)


DEFAULT_WEB = WebConfig()


@dataclass(frozen=True)
class FoxgloveConfig(Checked):
    """The live Foxglove server `services.foxglove`: where it serves and what one client may
    hold (the Foxglove SDK's server behind a relay of this process's own: a cap on clients,
    a handshake deadline, a per-client queue that drops the oldest messages)."""

    SECTION = "foxglove"
    host: str = "127.0.0.1"
    port: int = ranged(8765, 0, MAX_PORT)  # the Foxglove app's default; 0: any free port
    max_clients: int = ranged(8, 1)  # clients served at once; one more is answered 503
    # a client's WebSocket handshake (its HTTP upgrade request) must have arrived this long
    # after it connected, else it is closed
    handshake_timeout_s: float = positive(5.0)
    # a client that has taken none of what is sent to it for this long is closed
    send_timeout_s: float = positive(10.0)
    # messages queued per client in the SDK (its message_backlog_size, 1024 by default): when
    # full, the oldest is dropped (latest wins). The maps of a 363 x 537 world are ~0.2 MB
    # each, so a client that does not read holds ~30 MB here until it is closed. The SDK's
    # queue of advertisements has the same size, and a client it overflows is disconnected:
    # at 32, a client subscribing to 240 channels made at once was (test_foxglove_live.py)
    message_backlog: int = ranged(128, 1)
    # bytes this process buffers per client beyond what the kernel holds; above it, reading
    # from the SDK for that client pauses (so the SDK's queue, above, is the one that drops)
    client_buffer_bytes: int = ranged(2**18, 1)


DEFAULT_FOXGLOVE = FoxgloveConfig()


SERVICES_SECTION = "services"  # `--set services.FIELD=VALUE` reaches `RunConfig.services`


@dataclass(frozen=True)
class RunConfig(Checked):
    """Everything the processes of one run share: the exploration settings (the world's
    sensor and motion, the planners' methods and metrics) and the services section."""

    exploration: ExplorationConfig = field(default_factory=ExplorationConfig)
    services: ServicesConfig = field(default_factory=ServicesConfig)

    def with_overrides(self, overrides: list[str]) -> RunConfig:
        """This configuration with `--set` items applied: `services.FIELD=VALUE` to the
        services section, every other one to the exploration's (ConfigError, one line)."""
        config = self
        for item in overrides:
            section = item.partition("=")[0].partition(".")[0]
            path = item if section == SERVICES_SECTION else f"exploration.{item}"
            try:
                config = apply_overrides(config, [path])
            except ConfigError as error:
                message = str(error).replace(f"'{path}'", f"'{item}'")
                raise ConfigError(message.replace("exploration.", "")) from None
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
    add_override_argument(
        parser,
        "override a setting of the run (repeatable): an exploration field, e.g. "
        "motion.cells_per_step=2, or a services one, e.g. services.predict_timeout_s=20",
    )
