"""Ray for a batch: optional, local by default, or an existing cluster by address.

Ray is the `cluster` extra. `load_ray` returns None without it, and the batch then runs its objects
one after another in this process. An address is checked with a plain socket connection (a few
seconds at most) before `ray.init`, so a wrong one is reported instead of waited on.
"""

from __future__ import annotations

import os
import socket
from contextlib import contextmanager
from urllib.parse import urlsplit

from matspray.errors import SettingError

CONNECT_TIMEOUT_S = 3.0
GCS_PORT = 6379  # `ray start --head` default
CLIENT_PORT = 10001  # Ray Client (ray://) default
OBJECT_STORE_BYTES = 100 * 1024**2  # tasks return small dicts; the store needs little
INSTALL_HINT = "pip install 'matspray[cluster]'"


def load_ray():
    """The `ray` module, or None when it is not installed."""
    try:
        import ray
    except ImportError:
        return None
    return ray


def address_endpoint(address: str) -> tuple[str, int]:
    """(host, port) of a Ray address: 'host:port', 'host' (port 6379) or 'ray://host[:port]' (port 10001)."""
    client = address.startswith("ray://")
    parts = urlsplit(address if "://" in address else f"//{address}")
    try:
        port = parts.port
    except ValueError:
        raise SettingError(
            "address", f"the port of '{address}' is not a number; use HOST:PORT, e.g. 10.0.0.5:6379"
        ) from None
    if not parts.hostname:
        raise SettingError(
            "address", f"'{address}' has no host; use HOST:PORT, e.g. 10.0.0.5:6379, or ray://HOST:10001"
        )
    return parts.hostname, port or (CLIENT_PORT if client else GCS_PORT)


def check_reachable(address: str, timeout: float = CONNECT_TIMEOUT_S) -> None:
    """Raise SettingError when nothing accepts a connection at `address` within `timeout` seconds."""
    host, port = address_endpoint(address)
    try:
        with socket.create_connection((host, port), timeout=timeout):
            return
    except OSError as exc:
        reason = "no answer" if isinstance(exc, TimeoutError) else (exc.strerror or str(exc))
        raise SettingError(
            "address",
            f"nothing answers at {host}:{port} within {timeout:.0f} s ({reason}); start the "
            f"cluster's head there with `ray start --head --port={port}`, or leave the address out for a local Ray",
        ) from None


@contextmanager
def ray_session(ray, address: str | None, num_cpus: int, cpus_per_task: int, gpus_per_task: float):
    """Ray, started here (a local instance with `num_cpus` CPUs, shut down afterwards), joined at
    `address`, or the one this process already runs; refuses a task size the cluster cannot hold."""
    started = False
    if not ray.is_initialized():
        if address is not None:  # reachable: see check_reachable
            try:
                ray.init(address=address, logging_level="ERROR", log_to_driver=False)
            except (ConnectionError, RuntimeError) as exc:
                raise SettingError(
                    "address", f"Ray could not join the cluster at '{address}' ({' '.join(str(exc).split())[:200]})"
                ) from None
        else:
            # workers import this same matspray (a checkout need not be the installed copy)
            package_root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
            python_path = os.pathsep.join(p for p in (package_root, os.environ.get("PYTHONPATH")) if p)
            ray.init(
                num_cpus=num_cpus,
                object_store_memory=OBJECT_STORE_BYTES,
                include_dashboard=False,
                logging_level="ERROR",
                log_to_driver=False,
                runtime_env={"env_vars": {"PYTHONPATH": python_path}},
            )
        started = True
    try:
        resources = ray.cluster_resources()
        if resources.get("CPU", 0) < cpus_per_task:
            raise SettingError(
                "cpus_per_object",
                f"each object asks for {cpus_per_task} CPUs but the Ray cluster has {resources.get('CPU', 0):g}; "
                "lower the CPUs per object",
            )
        if resources.get("GPU", 0) < gpus_per_task:
            raise SettingError(
                "gpus_per_object",
                f"each object asks for {gpus_per_task:g} GPUs but the Ray cluster has {resources.get('GPU', 0):g}; "
                "lower the GPUs per object (0 runs on CPUs)",
            )
        yield ray
    finally:
        if started:
            ray.shutdown()
