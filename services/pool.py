"""A supervised local deployment, as `services.up` and `services.evaluate` start it.

Which Zenoh hub to use (serve tcp/127.0.0.1:7447 here, or join one that is already there
or given with --connect), the flags every child gets for it, the predictor-worker
processes of the pool, and the progress of the runs from what their processes publish.
"""

from __future__ import annotations

import argparse
import logging
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass

import zenoh

from mapex.config import ConfigError
from mapex.prediction import (
    DEFAULT_PREDICTOR,
    ORACLE,
    add_predictor_argument,
    inference_options,
    served_predictor_problem,
)
from mapex.prediction.base import MEMBER_NAMES
from mapex.prediction.config import (
    DEFAULT_INFERENCE,
    InferenceConfig,
    add_inference_arguments,
    inference_from_args,
)
from services.codec import ProtocolError
from services.config import ServicesConfig
from services.keys import RobotKey, RobotTopic, parse_key, robot_key_pattern
from services.messages import Message, decode_message
from services.supervisor import ProcessSpec, claim_hub, endpoint_silence
from services.zenoh_config import ZenohConfigError, config_file_endpoints, zenoh_config

log = logging.getLogger("services.pool")


def parse_member_list(text: str) -> tuple[str, ...]:
    """argparse type of --members: comma-separated member names, or 'none'."""
    if text == "none":
        return ()
    members = tuple(item.strip() for item in text.split(","))
    unknown = [m for m in members if m not in MEMBER_NAMES]
    if unknown:
        raise argparse.ArgumentTypeError(f"unknown member(s) {', '.join(unknown)}")
    return members


def add_pool_arguments(parser: argparse.ArgumentParser) -> None:
    """The predictor-pool flags of `services.up` and `services.evaluate`: which predictor,
    which members to spawn workers for, how many per member, their torch threads and how
    they run their networks (precision, inference path, views)."""
    add_predictor_argument(parser, served=True)
    parser.add_argument(
        "--members",
        type=parse_member_list,
        default=MEMBER_NAMES,
        help="members to spawn workers for, comma-separated, or 'none' (default: g,g1,g2,g3; "
        "the oracle's one worker serves g)",
    )
    parser.add_argument("--replicas", type=int, default=1, help="workers per member (default 1)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads per worker")
    add_inference_arguments(parser)


def resolve_pool_predictor(args: argparse.Namespace) -> None:
    """Check the pool flags against `--predictor` (ConfigError, one line): one the workers
    serve, network flags for a learned one only; under the oracle `args.members` becomes its
    one member, g (from the default of all four; 'none' stays none)."""
    if (problem := served_predictor_problem(args.predictor)) is not None:
        raise ConfigError(problem)
    inference_options(args.predictor, inference_from_args(args))
    if args.predictor != ORACLE or args.members in ((), MEMBER_NAMES[:1]):
        return
    if args.members != MEMBER_NAMES:
        raise ConfigError(
            f"--predictor oracle is served by member {MEMBER_NAMES[0]} only: --members "
            f"{MEMBER_NAMES[0]} or none"
        )
    args.members = MEMBER_NAMES[:1]


@dataclass(frozen=True)
class WorkerSpec(ProcessSpec):
    """A predictor-worker child: its member and the worker id it serves under."""

    member: str = ""
    worker_id: str = ""


def worker_specs(
    members: tuple[str, ...],
    replicas: int,
    threads: int,
    zenoh_flags: list[str],
    inference: InferenceConfig = DEFAULT_INFERENCE,
    id_prefix: str = "pool",
    settings: Sequence[str] = (),
    predictor: str = DEFAULT_PREDICTOR,
) -> list[WorkerSpec]:
    """`replicas` predictor workers per member, restarted when they die; worker ids
    `<id_prefix>-<member>-<replica>` (the supervisor probes their health under these).
    `settings`: the run's `--set` items (`RunConfig.as_overrides`); `predictor`: what they
    serve (the oracle's worker gets no network flags)."""
    sets = [flag for item in settings for flag in ("--set", item)]
    chosen = () if predictor == DEFAULT_PREDICTOR else ("--predictor", predictor)
    network = () if predictor == ORACLE else ("--threads", str(threads), *inference.flags())
    flags = (*chosen, *network, *sets, *zenoh_flags)
    specs = []
    for member in members:
        for replica in range(replicas):
            worker_id = f"{id_prefix}-{member}-{replica}"
            specs.append(
                WorkerSpec(
                    f"predictor-{member}" + (f"-{replica}" if replicas > 1 else ""),
                    "services.predictor",
                    ("--member", member, "--worker-id", worker_id, *flags),
                    restart=True,
                    member=member,
                    worker_id=worker_id,
                )
            )
    return specs


def adopt_config_file(args: argparse.Namespace) -> str | None:
    """Take the mode and endpoints of a `--config` file as the flags `--mode`, `--connect`
    and `--listen` that the command line leaves out, so that `services.up --config FILE`
    does what those flags would (a file's own session settings, TLS or a user name, stay in
    the file, which every session opens with): a file in client or peer mode that names
    connect endpoints joins that hub, probed first (`check_hub_answers`) and watched
    (`HubWatch`), as `--connect` does; one that names listen endpoints serves the hub there.
    Flags given still win. ZenohConfigError (one line) for a file that is in client mode
    with nowhere to connect to, or a router that connects elsewhere (a run either serves its
    hub or joins one). The file the connect endpoints came from, or None."""
    if not args.config or args.connect:
        return None
    file = config_file_endpoints(args.config, args.mode)
    mode = args.mode or file.mode
    if file.connect and mode == "router":
        raise ZenohConfigError(
            f"Zenoh config file {args.config} is a router that connects to "
            f"{', '.join(file.connect)}: give it mode client to join that hub (or --mode "
            f"client), or no connect endpoints to serve the hub here"
        )
    if not file.connect and mode == "client":
        raise ZenohConfigError(
            f"Zenoh config file {args.config} is in client mode but names no connect "
            f"endpoint: add the hub's (connect: {{ endpoints: [...] }}) or give --connect"
        )
    args.mode = mode
    if file.connect:
        args.connect = file.connect
        return args.config
    if args.listen is None and file.listen:
        args.listen = file.listen
    return None


def hub_session_config(
    args: argparse.Namespace, services: ServicesConfig
) -> tuple[zenoh.Config, list[str]]:
    """(Zenoh config of the supervisor's own session, Zenoh flags for every child).

    With --connect (or a `--config` file's connect endpoints: `adopt_config_file`),
    everyone joins that hub or router. Otherwise the supervisor serves the
    hub on --listen (default tcp/127.0.0.1:7447) as a Zenoh *router* and its children are
    clients of it: every message takes one hop through the router, and no peer-to-peer mesh
    forms, whose routes Zenoh re-computes (dropping queries in flight) whenever a
    short-lived peer such as an episode's planner joins or leaves. If the default hub
    endpoint is already taken (another supervisor), this is refused up front (a
    ZenohConfigError with the two ways out): a run that silently joined would lose its hub,
    and its results, when the other supervisor ends.
    """
    adopt_config_file(args)  # done already where the caller probed the hub first
    flags: list[str] = ["--config", args.config] if args.config else []
    if args.connect:  # a hub (router) elsewhere: everyone connects there
        flags += ["--mode", args.mode] if args.mode else []
        for endpoint in args.connect:
            flags += ["--connect", endpoint]
        own = zenoh_config(args.mode, args.connect, args.listen, args.config, services)
        return own, flags
    mode = args.mode or "router"
    flags += ["--mode", "client" if mode == "router" else mode]
    listen = args.listen or [services.hub_endpoint]
    if not args.listen and not claim_hub(services.hub_endpoint):
        hub = services.hub_endpoint
        raise ZenohConfigError(
            f"a hub already listens on {hub} (another services.up or services.evaluate?): "
            f"run beside it with --listen tcp/127.0.0.1:<free port>, or join it with --mode "
            f"client --connect {hub} (this run then ends when that one does)"
        )
    for endpoint in listen:
        flags += ["--connect", endpoint]
    return zenoh_config(mode, [], listen, args.config, services), flags


class HubWatch:
    """Whether the hub a run joined with `--connect` is still there: `services.up` and
    `services.evaluate` end the run with `lost()`'s line once their session has had no
    router for `ServicesConfig.hub_lost_grace_s` (the run that served the hub ended, or the
    router stopped). Otherwise a joined run went on without the hub's workers, its
    peer-mode children still linked to each other. A hub that was never seen to be a router
    (another supervisor's `--mode peer` hub) is not watched; nor is a hub served here."""

    def __init__(
        self, session: zenoh.Session, connect: Sequence[str] | None, services: ServicesConfig
    ) -> None:
        self.session = session
        self.endpoints = list(connect or ())
        self.grace_s = services.hub_lost_grace_s
        self._seen = False  # a router was linked once
        self._gone_since: float | None = None

    def lost(self) -> str | None:
        """The line that ends the run, or None while the hub is there (or not watched)."""
        if not self.endpoints:
            return None
        if any(True for _ in self.session.info.routers_zid()):
            self._seen, self._gone_since = True, None
            return None
        if not self._seen:
            return None
        now = time.monotonic()
        if self._gone_since is None:
            self._gone_since = now
        if now - self._gone_since < self.grace_s:
            return None
        return (
            f"the hub at --connect {' '.join(self.endpoints)} is gone (no router for "
            f"{self.grace_s:g} s: the run that served it ended, or the router stopped): "
            f"stopping the run"
        )


def check_hub_answers(
    connect: Sequence[str] | None, services: ServicesConfig, config_file: str | None = None
) -> None:
    """ZenohConfigError (one line) naming the first `--connect` endpoint where nothing
    accepts a connection within `services.hub_probe_timeout_s`, before any child starts:
    otherwise a peer-mode session opens anyway and the run waits for a world that can never
    answer (and a client-mode one gives up only after Zenoh's own retries). tcp/ and tls/
    endpoints are probed (`endpoint_silence`); None (no --connect) probes nothing.
    `config_file`: the `--config` file that named the endpoints (`adopt_config_file`)."""
    named = "" if config_file is None else f" (named in {config_file})"
    way_out = "leave out --connect" if config_file is None else "give a --config without it"
    for endpoint in connect or ():
        try:
            silence = endpoint_silence(endpoint, services.hub_probe_timeout_s)
        except ValueError as error:
            raise ZenohConfigError(f"bad --connect endpoint{named}: {error}") from None
        if silence is not None:
            raise ZenohConfigError(
                f"nothing answers at --connect {endpoint} ({silence}){named}: start the hub or "
                f"router there first, or {way_out} to serve the hub here"
            )


class RunProgress:
    """The latest step heard of every robot of every run, from one published topic.

    `topic` is one whose messages carry the step `t` (the world's `pose` every step, the
    planner's `metrics` every sample); malformed messages are logged and dropped.
    """

    def __init__(self, session: zenoh.Session, topic: RobotTopic, kind: type[Message]) -> None:
        self.kind = kind
        self._steps: dict[tuple[str, str], int] = {}  # (run, robot) -> latest t
        self._lock = threading.Lock()
        self._subscriber = session.declare_subscriber(robot_key_pattern(topic), self._on_sample)

    def of(self, run: str) -> int:
        """Steps done by the robots of `run`, all together."""
        with self._lock:
            return sum(t for (run_id, _), t in self._steps.items() if run_id == run)

    def close(self) -> None:
        self._subscriber.undeclare()

    def _on_sample(self, sample: zenoh.Sample) -> None:
        try:
            key = parse_key(str(sample.key_expr))
            message = decode_message(sample.payload.to_bytes(), (self.kind,))
        except ProtocolError as error:
            log.warning("dropped a progress message: %s", error)
            return
        if isinstance(key, RobotKey):
            with self._lock:
                robot = (key.run, key.robot)
                self._steps[robot] = max(self._steps.get(robot, 0), message.t)
