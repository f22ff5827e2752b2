"""The shipped access-control router (deploy/zenohd-acl.json5) as a real `python -m
deploy.router` process on loopback, and client sessions logged in with a role.

Two ways to log in, as deploy/README.md section 9 describes: `"password"` (user name and
password, transport.auth.usrpwd, checked against a temporary dictionary) and `"mtls"` (a
client certificate whose common name names the role, over mutual TLS, no passwords). The
shipped file is used as it is, apart from the dictionary path and, for mTLS, the TLS link
block of zenohd-tls.json5 with certificates made by openssl for localhost.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path

import pytest
import zenoh
from service_processes import (
    REPO_ROOT,
    RouterProcess,
    free_loopback_port,
    kill_router,
    wait_router_ready,
)

from services.zenoh_config import open_session, zenoh_config

ACL_FILE = REPO_ROOT / "deploy" / "zenohd-acl.json5"
DICTIONARY = "/etc/mapex/zenoh-users.txt"  # as written in ACL_FILE, replaced by a tmp file
ROLES = ("world", "worker", "planner", "runner", "viewer")
PASSWORDS = {role: f"{role}-s3cret" for role in ROLES}  # the user name is the role's
AUTHS = ("password", "mtls")
ROLE_CN_PREFIX = "mapex-"  # the certificate CN of role r is mapex-r
TLS_TRANSPORT = "transport: {"  # where the TLS link block goes in ACL_FILE (once)
LOOPBACK = "127.0.0.1"
LOOPBACK_NAMES = "DNS:localhost,IP:127.0.0.1"  # what the router's certificate names on loopback


def needs_openssl(auth: str) -> None:
    """Skip an mTLS case where the openssl command is missing."""
    if auth == "mtls" and shutil.which("openssl") is None:
        pytest.skip("needs the openssl command")


def start_acl_router(
    directory: Path,
    auth: str,
    edit=None,
    host: str = LOOPBACK,
    launcher: Sequence[str] = (),
) -> RouterProcess:
    """`python -m deploy.router --config <the shipped ACL file, adapted> --listen
    <loopback>` for `auth` ("password" or "mtls"), ready for clients; `RouterProcess.endpoint`
    is the endpoint clients connect to. `edit(text)`: a site's change to the file's text.
    `host`: the address to listen on instead of loopback (the router's certificate then names
    that address only), `launcher`: a command prefix, e.g. `ip netns exec NAME`."""
    text = ACL_FILE.read_text() if edit is None else edit(ACL_FILE.read_text())
    assert text.count(DICTIONARY) == 1 and text.count(TLS_TRANSPORT) == 1
    port = free_loopback_port()
    if auth == "password":
        users = directory / "zenoh-users.txt"
        users.write_text("".join(f"{role}:{PASSWORDS[role]}\n" for role in ROLES))
        text = text.replace(DICTIONARY, str(users))
        listen = client_endpoint = f"tcp/{host}:{port}"
    elif auth == "mtls":
        names = LOOPBACK_NAMES if host == LOOPBACK else f"IP:{host}"
        make_role_certificates(directory, tuple(ROLE_CN_PREFIX + role for role in ROLES), names)
        link = {
            "protocols": ["tls"],
            "tls": {
                "root_ca_certificate": str(directory / "ca.pem"),
                "listen_certificate": str(directory / "router.pem"),
                "listen_private_key": str(directory / "router-key.pem"),
                "enable_mtls": True,
            },
        }
        text = text.replace(f'"{DICTIONARY}"', "null")  # certificate CNs only
        text = text.replace(TLS_TRANSPORT, f"{TLS_TRANSPORT}\n    link: {json.dumps(link)},")
        listen = f"tls/{host}:{port}"
        client_endpoint = f"tls/localhost:{port}" if host == LOOPBACK else listen
    else:
        raise ValueError(f"unknown auth {auth!r}")
    config_file = directory / "zenohd-acl.json5"
    config_file.write_text(text)
    log_path = directory / "router.log"
    command = [sys.executable, "-m", "deploy.router", "--config", str(config_file)]
    with open(log_path, "wb") as log:
        process = subprocess.Popen(
            [*launcher, *command, "--listen", listen], cwd=REPO_ROOT, stdout=log, stderr=log
        )
    router = RouterProcess(process, log_path, client_endpoint)
    try:
        wait_router_ready(router)
    except BaseException:
        kill_router(router)
        raise
    return router


def role_config(router: RouterProcess, directory: Path, auth: str, role: str) -> zenoh.Config:
    """The client config of one process of `role` joining `router` by `auth`."""
    config = zenoh_config("client", [router.endpoint])
    if auth == "password":
        credentials = {"user": role, "password": PASSWORDS[role]}
        config.insert_json5("transport/auth/usrpwd", json.dumps(credentials))
    else:
        cn = ROLE_CN_PREFIX + role
        files = {
            "root_ca_certificate": str(directory / "ca.pem"),
            "connect_certificate": str(directory / f"{cn}.pem"),
            "connect_private_key": str(directory / f"{cn}-key.pem"),
            "enable_mtls": True,
        }
        config.insert_json5("transport/link/protocols", json.dumps(["tls"]))
        config.insert_json5("transport/link/tls", json.dumps(files))
    return config


def role_session(router: RouterProcess, directory: Path, auth: str, role: str) -> zenoh.Session:
    """A client session of `role` on `router`."""
    return open_session(role_config(router, directory, auth, role))


def make_role_certificates(
    directory: Path, names: tuple[str, ...], router_names: str = LOOPBACK_NAMES
) -> None:
    """A CA, a router certificate whose subjectAltName is `router_names` (openssl's form)
    and a client certificate per CN in `names` (P-256, X.509 v3 with a subjectAltName:
    Zenoh's TLS refuses v1)."""
    new_key = ["req", "-nodes", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1"]
    _openssl(
        directory, *new_key, "-x509", "-subj", "/CN=ca", "-keyout", "ca-key.pem", "-out", "ca.pem"
    )
    (directory / "router.ext").write_text(f"subjectAltName={router_names}\n")
    (directory / "san.ext").write_text(f"subjectAltName={LOOPBACK_NAMES}\n")
    sign = ["x509", "-req", "-CA", "ca.pem", "-CAkey", "ca-key.pem", "-CAcreateserial"]
    for name in ("router", *names):
        key, request = f"{name}-key.pem", f"{name}.csr"
        extensions = "router.ext" if name == "router" else "san.ext"
        _openssl(directory, *new_key, "-subj", f"/CN={name}", "-keyout", key, "-out", request)
        _openssl(directory, *sign, "-extfile", extensions, "-in", request, "-out", f"{name}.pem")


def _openssl(directory: Path, *args: str) -> None:
    subprocess.run(["openssl", *args], cwd=directory, check=True, capture_output=True)
