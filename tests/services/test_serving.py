"""services.serving: an answer that raises is one warning and an `error` reply, and the
key's thread answers the next query (the world and the predictor workers answer through it)."""

from __future__ import annotations

import logging

from services.messages import ErrorReply, PoseMessage, decode_message
from services.serving import QueryServers
from services.zenoh_config import open_session, zenoh_config

KEY = "mapex/@v1/serving_test/r0/pose"
QUERY_TIMEOUT_S = 5.0


def _answer(payload, _waited_s):
    if payload == b"boom":
        raise ValueError("an input nobody\nforesaw")
    if payload == b"unencodable":
        return PoseMessage.__new__(PoseMessage)  # no fields: encoding it raises
    return PoseMessage(3, (1, 2))


def _ask(session, payload: bytes):
    replies = list(session.get(KEY, payload=payload, timeout=QUERY_TIMEOUT_S))
    assert len(replies) == 1
    sample = replies[0].ok if replies[0].ok is not None else replies[0].err
    return decode_message(sample.payload.to_bytes())


def test_an_answer_that_raises_is_one_warning_and_an_error_reply(hub, caplog):
    servers = QueryServers(hub[0], {KEY: _answer})
    client = open_session(zenoh_config(connect=[hub[1]], listen=[]))
    try:
        with caplog.at_level(logging.WARNING, logger="services.serving"):
            for payload in (b"boom", b"unencodable", b"boom"):
                reply = _ask(client, payload)
                assert isinstance(reply, ErrorReply), payload
                assert reply.message == f"{KEY}: the query could not be answered"
            assert _ask(client, b"fine") == PoseMessage(3, (1, 2))  # the thread goes on
    finally:
        client.close()
        servers.close(1.0)
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 3 and all("\n" not in w for w in warnings), warnings
    assert f"{KEY}: could not answer a query: ValueError: an input nobody foresaw" in warnings
    assert not any(thread.is_alive() for thread in servers.threads)  # closed cleanly
