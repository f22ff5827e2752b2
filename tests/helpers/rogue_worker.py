"""A rogue predictor worker for tests: a real process that misbehaves as told.

    python -m rogue_worker --member g1 --worker-id a-rogue --mode zeros|poison|lie|drop
        [--claim-id ID] [--on-key ID] [--delay S] [--redeclare] --connect ENDPOINT

It declares what an honest worker declares (the `predict` queryable, the `health` queryable
and the liveliness token) under its own id, prints "ready", then one line "query N" for every
prediction query it receives, and:

* zeros: answers every query at once with an all-free (all-zero) map, signed `--claim-id`
  (default: its own id), as a rogue claiming a legitimate worker's answers would;
* lie: never answers a query (holds it until the querier times out) while its health replies
  say it is idle, as a worker lying to be taken back would;
* poison: answers with the known cells of the crop copied through (walls 1, free 0) and
  random values on the unknown ones, which no check of the known cells can tell;
* drop: drops every query at once without a reply.

`--on-key ID` serves the predict key of worker ID (another's) instead of its own, declaring
no token; `--delay S` answers S seconds late; `--redeclare` undeclares and declares its
liveliness token again after each answer, as a rogue shaking off its bench would.

Its health replies always say idle (busy 0). It stops on SIGINT/SIGTERM.
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
import time

import numpy as np
import zenoh

from mapex.grid import FREE, OCCUPIED
from services.keys import alive_predictor_key, health_key, predict_key
from services.messages import HealthReply, PredictReply, PredictRequest
from services.zenoh_config import ZenohConfigError, open_session, zenoh_config

CONNECT_DEADLINE_S = 60.0  # the hub may still be starting (services.up serves it)
CONNECT_RETRY_S = 0.2
REDECLARE_PAUSE_S = 0.2
REDECLARE_AFTER_S = 0.3


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--member", required=True)
    parser.add_argument("--worker-id", required=True)
    parser.add_argument("--mode", choices=("zeros", "poison", "lie", "drop"), required=True)
    parser.add_argument("--claim-id", default=None)
    parser.add_argument("--on-key", default=None)
    parser.add_argument("--delay", type=float, default=0.0)
    parser.add_argument("--redeclare", action="store_true")
    parser.add_argument("--connect", required=True)
    args = parser.parse_args()
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    session = _connect(args.connect)
    claimed = args.claim_id or args.on_key or args.worker_id
    key = predict_key(args.member, args.on_key or args.worker_id)
    rng = np.random.default_rng(7)
    token = None
    held: list[zenoh.Query] = []  # lie: queries kept unanswered (never finalised)
    received = 0
    lock = threading.Lock()

    def on_query(query: zenoh.Query) -> None:
        nonlocal received
        with lock:
            received += 1
            print(f"query {received}", flush=True)
        if args.mode == "lie":
            held.append(query)
        elif args.mode in ("zeros", "poison"):
            request = PredictRequest.decode(query.payload.to_bytes())
            answer = np.zeros(request.observed.shape, dtype=np.float32)
            if args.mode == "poison":
                answer = rng.random(answer.shape).astype(np.float32)
                answer[request.observed == OCCUPIED], answer[request.observed == FREE] = 1, 0
            reply = PredictReply.from_probabilities(
                request.request_id, args.member, answer, claimed, 1.0
            )
            time.sleep(args.delay)
            query.reply(key, reply.encode())
            if args.redeclare:  # once the querier has judged the answer
                threading.Timer(REDECLARE_AFTER_S, redeclare).start()
        # drop: the query is released unanswered when this callback returns

    def on_probe(query: zenoh.Query) -> None:
        health = HealthReply(args.member, args.worker_id, 0.0, 0, received, 0)
        query.reply(query.key_expr, health.encode())

    def redeclare() -> None:
        nonlocal token
        if token is not None:
            token.undeclare()
            time.sleep(REDECLARE_PAUSE_S)  # the token's end reaches every subscriber
        token = session.liveliness().declare_token(alive_key)

    alive_key = alive_predictor_key(args.member, args.worker_id)
    queryable = session.declare_queryable(key, on_query)
    probe = session.declare_queryable(health_key(args.member, args.worker_id), on_probe)
    if args.on_key is None:
        redeclare()
    print("ready", flush=True)
    while not stop.wait(0.1):
        pass
    if token is not None:
        token.undeclare()
    probe.undeclare()
    queryable.undeclare()
    held.clear()
    session.close()
    return 0


def _connect(endpoint: str) -> zenoh.Session:
    deadline = time.monotonic() + CONNECT_DEADLINE_S
    while True:
        try:
            return open_session(zenoh_config(mode="client", connect=[endpoint], listen=[]))
        except ZenohConfigError:  # nothing listens there yet
            if time.monotonic() > deadline:
                raise
            time.sleep(CONNECT_RETRY_S)


if __name__ == "__main__":
    sys.exit(main())
