"""A predictor worker: serves prediction queries for one ensemble member over Zenoh.

    python -m services.predictor --member g [--predictor lama|lama-v2|oracle]
        [--worker-id ID] [--weights-dir DIR] [--device cpu|cuda] [--threads 1]
        [--precision float32|bfloat16] [--inference fused|plain] [--views 1|2]
        [--hang-after N] [--mode ...] [--connect ...] [--listen ...]

It answers `predict` queries one at a time on a serving thread and health probes at once;
replicas of a member share the load. `--predictor oracle` (member g only) answers with the
ground truth of the run a request names, read from its world, and loads no torch
(services/oracle_worker.py). Keys and replies: docs/protocol.md; threads, fault injection
and exits: docs/design.md#processes; health and benching: docs/design.md#reliability.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import re
import socket
import sys
import threading
import time
from pathlib import Path
from typing import NoReturn

import numpy as np
import zenoh

from mapex.config import ConfigError, WorldConfig
from mapex.exit_codes import EXIT_USAGE
from mapex.prediction import (
    DEFAULT_PREDICTOR,
    ORACLE,
    ORACLE_NOTICE,
    add_predictor_argument,
    inference_options,
    make_predictor,
    served_predictor_problem,
)
from mapex.prediction.base import MEMBER_NAMES, Predictor
from mapex.prediction.config import (
    DEFAULT_INFERENCE,
    InferenceConfig,
    add_inference_arguments,
    inference_from_args,
)
from services.codec import DEFAULT_SERVICES, Payload, ProtocolError, quantise_probability
from services.config import RunConfig, ServicesConfig, add_run_config_argument
from services.keys import (
    ID_MAX_CHARS,
    MEMBERS,
    alive_predictor_key,
    health_key,
    is_valid_id,
    predict_key,
)
from services.messages import (
    ErrorReply,
    HealthReply,
    PredictReply,
    PredictRequest,
    map_message_bytes,
)
from services.oracle_worker import (
    GroundTruths,
    OracleMember,
    RequestRefusedError,
    zenoh_truth_source,
)
from services.serving import (
    QueryServers,
    configure_logging,
    exit_on_signals,
    return_freed_memory,
    stop_on_signals,
    wait_for,
)
from services.zenoh_config import (
    ZenohConfigError,
    add_zenoh_arguments,
    open_session,
    zenoh_config_from_args,
)

_DEVICE_PATTERN = re.compile(r"cpu|cuda(:\d+)?")

DEFAULT_MAX_CELLS = WorldConfig().max_cells  # the largest world a request's crop may be of

log = logging.getLogger("services.predictor")


class MemberServer:
    """Turns one request payload into the reply of one member; knows nothing of Zenoh.

    `predictor` is a `Predictor` of crops (the learned ensemble's member) or the oracle's
    member (`services.oracle_worker.OracleMember`, which reads where the crop lies); `serves`
    names the predictor it is (`lama`, `lama-v2`, `oracle`): a request for another is refused,
    so a planner never takes one predictor's answer for another's.

    The ensemble keeps its last answers by crop (`mapex.prediction.recent`): the planners of
    a team hold the same merged map, so at a step where several of them ask for the same
    crop (the metrics' whole-map prediction, above all) it is computed once; the network is
    deterministic, so the answer is the one it would compute again. Tracks what a health
    probe reports: the start of the prediction being computed, the
    predictions answered and the requests dropped past their budget. `hang_after` (fault
    injection) makes it block for ever once it has answered that many.
    """

    def __init__(
        self,
        predictor: Predictor | OracleMember,
        member: str,
        worker_id: str,
        hang_after: int | None = None,
        serves: str = DEFAULT_PREDICTOR,
        max_cells: int = DEFAULT_MAX_CELLS,
    ) -> None:
        self.predictor = predictor
        self.max_request_bytes = map_message_bytes(max_cells)  # a crop of the largest world
        self.serves = serves
        self.member = member
        self.worker_id = worker_id
        self.hang_after = hang_after
        self.answered = 0  # predictions served
        self.dropped = 0  # requests that waited past their budget
        self._busy_since: float | None = None  # monotonic start of the current prediction

    def answer(self, payload: Payload | None, waited_s: float = 0.0) -> PredictReply | ErrorReply:
        """The PredictReply for a valid PredictRequest payload, else an ErrorReply saying why.

        `waited_s`: how long the request waited queued; past its budget it is dropped.
        """
        try:
            if payload is None:
                raise ProtocolError("the query carries no payload")
            request = PredictRequest.decode(payload, max_bytes=self.max_request_bytes)
        except ProtocolError as error:
            log.warning("refused a malformed request: %s", error)
            return ErrorReply(f"malformed predict request: {error}")
        if request.budget_s is not None and waited_s > request.budget_s:
            self.dropped += 1
            log.warning(
                "dropped request %d: it waited %.1f s, past its %.1f s budget",
                request.request_id, waited_s, request.budget_s,
            )  # fmt: skip
            return ErrorReply(
                f"dropped: waited {waited_s:.1f} s, past the {request.budget_s} s budget"
            )
        wanted = request.predictor or DEFAULT_PREDICTOR
        if wanted != self.serves:
            log.warning("refused request %d of predictor %s", request.request_id, wanted)
            return ErrorReply(f"this worker serves predictor {self.serves}, not {wanted}")
        self._busy_since = time.monotonic()
        try:
            return self._predict(request)
        finally:
            self._busy_since = None

    def health(self, queued: int) -> HealthReply:
        """What a health probe is told now (`queued`: requests waiting behind this one)."""
        since = self._busy_since
        busy_s = 0.0 if since is None else time.monotonic() - since
        return HealthReply(self.member, self.worker_id, busy_s, queued, self.answered, self.dropped)

    def _predict(self, request: PredictRequest) -> PredictReply | ErrorReply:
        if self.hang_after is not None and self.answered >= self.hang_after:
            log.warning("fault injection: hanging on request %d", request.request_id)
            threading.Event().wait()  # for ever, as a deadlocked worker would
        started = time.perf_counter()
        try:
            probabilities = self._probabilities(request)
            quantised = quantise_probability(probabilities)
            compute_ms = (time.perf_counter() - started) * 1e3
            reply = PredictReply(
                request.request_id, self.member, quantised, self.worker_id, compute_ms
            )
        except RequestRefusedError as error:
            log.warning("refused request %d: %s", request.request_id, error)
            return ErrorReply(f"refused: {error}")
        except Exception as error:  # a failed prediction must not take the worker down
            log.exception("prediction of request %d failed", request.request_id)
            return ErrorReply(f"prediction failed: {type(error).__name__}: {error}")
        self.answered += 1
        return reply

    def _probabilities(self, request: PredictRequest) -> np.ndarray:
        """The member's probabilities for the request's crop: a predictor of crops reads the
        crop alone, the oracle also where in which run it lies."""
        if isinstance(self.predictor, OracleMember):
            return self.predictor.predict_request(request)
        return self.predictor.predict_members(request.observed, (0,))[0]


def serve(
    session: zenoh.Session,
    server: MemberServer,
    stop: threading.Event,
    services: ServicesConfig = DEFAULT_SERVICES,
) -> int:
    """Serve `server`'s member on `session` until `stop` is set; return the queries answered."""
    key = predict_key(server.member, server.worker_id)
    servers = QueryServers(session, {key: server.answer})

    def on_probe(query: zenoh.Query) -> None:  # on Zenoh's thread: never waits for a prediction
        query.reply(query.key_expr, server.health(servers.queued(key)).encode())

    probe = session.declare_queryable(health_key(server.member, server.worker_id), on_probe)
    token = session.liveliness().declare_token(alive_predictor_key(server.member, server.worker_id))
    log.info("serving member %s on %s", server.member, key)
    try:
        wait_for(stop)
    finally:
        token.undeclare()
        probe.undeclare()
        servers.close(services.predictor_drain_s)
        if any(thread.is_alive() for thread in servers.threads):  # its querier gets no reply
            log.warning(
                "stopping without the prediction in progress (still computing after the "
                "%g s drain)", services.predictor_drain_s,
            )  # fmt: skip
    return server.answered


def main(
    config: zenoh.Config,
    member: str,
    worker_id: str,
    weights_dir: Path | None = None,
    device: str = "cpu",
    threads: int = DEFAULT_SERVICES.predictor_threads,
    stop: threading.Event | None = None,
    services: ServicesConfig = DEFAULT_SERVICES,
    inference: InferenceConfig = DEFAULT_INFERENCE,
    hang_after: int | None = None,
    predictor: str = DEFAULT_PREDICTOR,
    max_cells: int = DEFAULT_MAX_CELLS,
) -> int:
    """Load `member` of `predictor` (its weights, from `weights_dir` or the predictor's own
    folder), then serve it until `stop` is set; return the queries answered. The oracle
    loads nothing: it reads each run's ground truth when first asked. A request larger
    than a crop of `max_cells` cells (`world.max_cells`) is refused unread.

    Raises ConfigError (missing or broken weights, settings of a network the predictor does
    not run) or ZenohConfigError (session refused). The weights load before the session
    opens, so a bad file costs no network set-up.
    """
    return_freed_memory()
    model: Predictor | OracleMember | None = None  # the oracle's needs the session
    if predictor != ORACLE:
        model = _learned_member(predictor, member, weights_dir, device, threads, inference)
    if stop is not None and stop.is_set():  # stopped while loading: never serve
        return 0
    session = open_session(config)
    try:
        if model is None:
            log.info("%s", ORACLE_NOTICE)
            truths = GroundTruths(zenoh_truth_source(session, services), services.oracle_runs_kept)
            model = OracleMember(truths)
        server = MemberServer(
            model, member, worker_id, hang_after, serves=predictor, max_cells=max_cells
        )
        return serve(session, server, stop or threading.Event(), services)
    finally:
        session.close()


def _learned_member(
    predictor: str,
    member: str,
    weights_dir: Path | None,
    device: str,
    threads: int,
    inference: InferenceConfig,
) -> Predictor:
    """`member` of the learned `predictor`, loaded (torch is imported here, so the oracle
    worker never loads it); a missing or broken weights file is a ConfigError (one line)."""
    from mapex.prediction.weights import WeightsError

    options = {"members": (member,), **inference_options(predictor, inference)}
    if weights_dir is not None:
        options["weights_dir"] = Path(weights_dir)
    try:
        return make_predictor(predictor, device=device, threads=threads, **options)
    except WeightsError as error:
        raise ConfigError(str(error)) from None


def default_worker_id() -> str:
    """`<host>-<pid>`, lower-cased and reduced to the characters a worker id may hold."""
    host = re.sub(r"[^a-z0-9_-]+", "-", socket.gethostname().lower()).strip("-") or "host"
    suffix = f"-{os.getpid()}"
    return host[: ID_MAX_CHARS - len(suffix)] + suffix


def build_parser() -> argparse.ArgumentParser:
    """The command-line flags: member, worker id, weights, device, threads and Zenoh's."""
    parser = argparse.ArgumentParser(
        prog="python -m services.predictor", description=__doc__.splitlines()[0]
    )
    parser.add_argument("--member", required=True, choices=MEMBERS, help="ensemble member")
    add_predictor_argument(parser, served=True)
    parser.add_argument("--worker-id", default=None, help="unique id (default: <host>-<pid>)")
    parser.add_argument(
        "--weights-dir",
        type=Path,
        default=None,
        help="<member>.pt here (default: the predictor's folder, mapex/prediction/weights/ for "
        "lama, its v2/ for lama-v2)",
    )
    parser.add_argument("--device", default="cpu", help="torch device: cpu, cuda or cuda:N")
    parser.add_argument(
        "--threads",
        type=int,
        default=None,
        help="torch CPU threads (default: services.predictor_threads, one, as several "
        "workers share the machine)",
    )
    add_inference_arguments(parser)
    add_run_config_argument(parser)
    parser.add_argument(
        "--hang-after",
        type=int,
        default=None,
        metavar="N",
        help="fault injection (tests, benchmarks): stop answering after N predictions, "
        "keeping the session, token and health probe",
    )
    add_zenoh_arguments(parser)
    return parser


def run_cli(argv: list[str] | None = None) -> int:
    """Parse flags, serve until SIGINT/SIGTERM; 0 on a clean stop, 2 on a one-line error."""
    parser = build_parser()
    args = parser.parse_args(argv)
    worker_id = args.worker_id or default_worker_id()
    _check_flags(parser, args, worker_id)
    configure_logging(f"predictor[{args.member}/{worker_id}]")
    stop = stop_on_signals()
    try:
        run_config = RunConfig().with_overrides(args.overrides)
        services = run_config.services
        log.info("%s", run_config.describe())
        config = zenoh_config_from_args(args, services)
        answered = main(
            config,
            args.member,
            worker_id,
            args.weights_dir,
            args.device,
            args.threads or services.predictor_threads,
            stop,
            services,
            inference=inference_from_args(args),
            hang_after=args.hang_after,
            predictor=args.predictor,
            max_cells=run_config.exploration.world.max_cells,
        )
    except (ConfigError, ZenohConfigError) as error:
        log.error("%s", error)
        return EXIT_USAGE
    log.info("stopped after answering %d queries", answered)
    return 0


def exit_now(code: int) -> NoReturn:
    """End the process with `code` at once, without the interpreter's teardown.

    A stopped worker has nothing left to save (its session is closed, its replies sent), but
    tearing down torch's thousands of modules takes seconds on a loaded machine, longer than
    services.up's `stop_grace_s`, and would wait on a thread still computing a prediction
    that nobody will read: the supervisor would SIGKILL a worker that had stopped cleanly.
    """
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(OSError, ValueError):
            stream.flush()
    os._exit(code)


def _check_flags(parser: argparse.ArgumentParser, args: argparse.Namespace, worker_id: str) -> None:
    """argparse-style one-line errors (exit 2) for flag values argparse cannot check itself."""
    if not is_valid_id(worker_id):
        parser.error(f"--worker-id {worker_id!r} must match [a-z0-9_-]{{1,{ID_MAX_CHARS}}}")
    if not _DEVICE_PATTERN.fullmatch(args.device):
        parser.error(f"--device {args.device!r} must be cpu, cuda or cuda:N")
    if args.threads is not None and args.threads < 1:
        parser.error(f"--threads must be at least 1, got {args.threads}")
    if args.hang_after is not None and args.hang_after < 0:
        parser.error(f"--hang-after must be at least 0, got {args.hang_after}")
    if (problem := served_predictor_problem(args.predictor)) is not None:
        parser.error(problem)
    if args.predictor == ORACLE:
        _check_oracle_flags(parser, args)
        return
    if args.device.startswith("cuda") and not _cuda_available():
        parser.error(f"--device {args.device}: no CUDA device is available")


def _check_oracle_flags(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """The oracle serves member g and runs no network: no weights, device or network flags."""
    if args.member != MEMBER_NAMES[0]:
        parser.error(f"--predictor oracle is served by member {MEMBER_NAMES[0]} only")
    if args.weights_dir is not None or args.device != "cpu":
        parser.error("--predictor oracle reads the ground truth: no --weights-dir or --device")
    try:
        inference_options(ORACLE, inference_from_args(args))
    except ConfigError as error:
        parser.error(str(error))


def _cuda_available() -> bool:
    import torch

    return torch.cuda.is_available()


if __name__ == "__main__":
    # From here a signal ends the process at once until it serves: loading torch's weights
    # takes seconds on a loaded machine, and a worker stopped then would finish loading
    # first and outlast services.up's grace period (the graceful stop begins with serving).
    exit_on_signals(until_serving=True)
    exit_now(run_cli())
