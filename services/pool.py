"""A supervised local deployment, as `services.up` and `services.evaluate` start it.

Which Zenoh hub to use (serve tcp/127.0.0.1:7447 here, or join one that is already there
or given with --connect), the flags every child gets for it, and the predictor-worker
processes of the pool.
"""

from __future__ import annotations

import argparse
import logging

import zenoh

from mapex.config import ServicesConfig
from mapex.prediction.base import MEMBER_NAMES
from services.supervisor import ProcessSpec, claim_hub
from services.zenoh_config import zenoh_config

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


def worker_specs(
    members: tuple[str, ...], replicas: int, threads: int, zenoh_flags: list[str]
) -> list[ProcessSpec]:
    """`replicas` predictor workers per member, restarted when they die."""
    return [
        ProcessSpec(
            f"predictor-{member}" + (f"-{replica}" if replicas > 1 else ""),
            "services.predictor",
            ("--member", member, "--threads", str(threads), *zenoh_flags),
            restart=True,
        )
        for member in members
        for replica in range(replicas)
    ]


def hub_session_config(
    args: argparse.Namespace, services: ServicesConfig
) -> tuple[zenoh.Config, list[str]]:
    """(Zenoh config of up's own session, flags for the children)."""
    flags: list[str] = []
    if args.mode:
        flags += ["--mode", args.mode]
    if args.config:
        flags += ["--config", args.config]
    if args.connect:  # a hub (router) elsewhere: everyone connects there
        for endpoint in args.connect:
            flags += ["--connect", endpoint]
        own = zenoh_config(args.mode, args.connect, args.listen, args.config, services)
        return own, flags
    listen = args.listen or [services.hub_endpoint]
    if args.listen or claim_hub(services.hub_endpoint):
        for endpoint in listen:
            flags += ["--connect", endpoint]
        return zenoh_config(args.mode, [], listen, args.config, services), flags
    log.info("a hub already listens on %s: joining it", services.hub_endpoint)
    return zenoh_config(args.mode, None, None, args.config, services), flags
