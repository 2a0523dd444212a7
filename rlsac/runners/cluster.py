"""The Ray cluster the stages run on: a local one started, or one joined (its address and the tracking
server checked first), and the resources the stages ask for."""

from __future__ import annotations

import fnmatch
import os
import time
from pathlib import Path
from typing import Any

from rlsac.errors import RlsacError

ADDRESS_TIMEOUT_S = 10.0  # an unreachable --address (a head still starting gets this long): Ray retried for minutes


def _check_tracking_server() -> None:
    """Stages on other machines log where MLFLOW_TRACKING_URI points: a sqlite file (the default) would be one store
    per node and the driver's a third, with no warning (issue #50, item 3), so a cluster needs an http(s) server."""
    from urllib.parse import urlsplit

    from rlsac.tracking import DEFAULT_URI

    uri = os.environ.get("MLFLOW_TRACKING_URI") or DEFAULT_URI
    if urlsplit(uri).scheme.lower() not in ("http", "https"):
        raise RlsacError(f"--address runs stages on other machines: MLFLOW_TRACKING_URI must be an http(s) MLflow "
                         f"server every node reaches, not {uri} (one store per node; docs/reproducing.md shows the "
                         "server command)")


def _auto_address() -> tuple[str, str]:
    """The address Ray's ``auto`` joins, found as ``ray.init`` finds it: RAY_ADDRESS, else the address file the last
    ``ray start`` (or a local cluster) wrote in Ray's temporary folder (ray_current_cluster; a killed cluster leaves it
    behind), else a Ray cluster process of this machine. -> (the address, where it was found)."""
    if os.environ.get("RAY_ADDRESS"):
        return os.environ["RAY_ADDRESS"], "from RAY_ADDRESS"
    from ray._common.utils import get_ray_address_file
    from ray._private.services import canonicalize_bootstrap_address

    try:
        address = canonicalize_bootstrap_address("auto")
    except Exception as e:  # noqa: BLE001 (Ray's ConnectionError when there is none; a bad file's ValueError)
        raise RlsacError(f"--address auto: no Ray cluster to join ({' '.join(str(e).split())[:160]})") from None
    file = get_ray_address_file(None)
    return address, f"from {file}" if Path(file).is_file() else "a Ray process of this machine"


def _check_address(address: str, shown: str | None = None) -> None:
    """A TCP connection to ``address`` (host:port, or ray://host:port) within ``ADDRESS_TIMEOUT_S``, retried while
    refused (a head started just before): Ray's own connection retried for over 400 s, with the MLflow run open.
    ``shown``: the option's value in the error, when not ``address`` (``auto`` and what it stood for)."""
    import socket
    from urllib.parse import urlsplit

    shown = shown or address
    where = urlsplit(address if "://" in address else f"ray://{address}")
    try:
        host, port = where.hostname, where.port
    except ValueError:  # a port that is not a number
        host, port = None, None
    if not host or not port:
        raise RlsacError(f"--address {shown}: not host:port (`ray start --head` prints the address), nor 'auto'")
    end = time.monotonic() + ADDRESS_TIMEOUT_S
    while True:
        try:
            socket.create_connection((host, port), timeout=max(0.1, end - time.monotonic())).close()
            return
        except OSError as e:
            if time.monotonic() + 0.5 >= end:
                raise RlsacError(f"--address {shown}: no Ray cluster answers there within {ADDRESS_TIMEOUT_S:g} s "
                                 f"({e.__class__.__name__}: {' '.join(str(e).split())[:120]})") from None
            time.sleep(0.5)


def _check_resources(o: dict, plan: dict, resources: dict) -> None:
    """What the stages ask Ray for must exist in the cluster, else a task waits for ever."""
    gpu_stages = [a for a in plan["todo"] if o["gpus_per_train"] > 0 and _is_gpu_stage(a, o["gpu_stages"])]
    if gpu_stages and resources.get("GPU", 0) < o["gpus_per_train"]:
        raise RlsacError(f"--gpus-per-train {o['gpus_per_train']:g}: the Ray cluster has "
                         f"{resources.get('GPU', 0):g} GPUs ({gpu_stages[0]} would never start)")


def _start_ray(o: dict) -> tuple[Any, bool]:
    """-> (ray, started): joins ``address``, or starts a local cluster of ``workers`` CPUs; an already
    initialised Ray (a test, a notebook) is used as it is and left running."""
    import logging

    if o["address"] and o["address"] != "auto" and "RAY_AUTH_MODE" not in os.environ and (
            os.environ.get("RAY_AUTH_TOKEN") or os.environ.get("RAY_AUTH_TOKEN_PATH")
            or (Path.home() / ".ray" / "auth_token").is_file()):
        # Ray uses the cluster token (RAY_AUTH_TOKEN, ~/.ray/auth_token) by itself for `auto` only; for an explicit
        # address it must be asked for, before Ray is imported (its configuration is read then)
        os.environ["RAY_AUTH_MODE"] = "token"
    import ray

    if ray.is_initialized():
        return ray, False
    kwargs = {"include_dashboard": False, "logging_level": logging.WARNING, "log_to_driver": False}
    try:
        if o["address"]:
            ray.init(address=o["address"], **kwargs)
        else:  # a local cluster: token authentication stays on, its notice is noise on this screen
            auth_log = logging.getLogger("ray._private.authentication.authentication_token_setup")
            level = auth_log.level
            auth_log.setLevel(logging.ERROR)
            try:
                # address="local": a new cluster even where `ray start` left one running (or its address file)
                ray.init(address="local", num_cpus=o["workers"] or os.cpu_count() or 1, **kwargs)
            finally:
                auth_log.setLevel(level)
    except Exception as e:
        raise RlsacError(f"cannot start Ray{' at ' + o['address'] if o['address'] else ''} "
                         f"({e.__class__.__name__}: {' '.join(str(e).split())[:200]})") from None
    return ray, True


def _is_gpu_stage(address: str, patterns: str) -> bool:
    return any(fnmatch.fnmatchcase(address, p.strip()) for p in patterns.split(",") if p.strip())
