"""Executors: where the cached stage units run.

A *unit* is one call of :meth:`harness.runtime.cache.StageCache.run` (a stage name, the parts of
its key and a build function that fills a temporary directory). Units are independent and write
their output atomically, so they can run anywhere that sees the same filesystem, in any order, and
a rerun skips the finished ones.

- ``local`` (default): one after the other in this process.
- ``ray``: each unit is a Ray task (``pip install 'dbl-harness[ray]'``); a worker that dies is
  retried by Ray (``max_retries``); units of the descriptor and ranking stages ask for a GPU when
  the cluster has one.
"""

from __future__ import annotations

import logging
import os
import socket
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from harness.errors import ConfigError, HarnessError
from harness.runtime.cache import StageCache

log = logging.getLogger(__name__)

Unit = tuple[tuple[Any, ...], Callable[[Path], dict | None]]


def run_unit(
    root: str, name: str, parts: tuple, build: Callable[[Path], dict | None]
) -> tuple[str, bool]:
    """Run one cached unit (in whatever process the executor chose); returns (directory, ran)."""
    path, ran = StageCache(Path(root)).run(name, parts, build)
    return str(path), ran


class LocalExecutor:
    """Builds units one after another in this process."""

    name = "local"

    def describe(self) -> dict[str, Any]:
        """What ran the units, for ``run.json``."""
        return {"name": "local", "workers": 1}

    def map_units(
        self, cache: StageCache, name: str, units: list[Unit], gpu: bool = False
    ) -> list[tuple[Path, bool]]:
        """Build every unit not yet in ``cache`` (in order).

        Returns:
            (entry path, whether it was built now) per unit.
        """
        del gpu
        return [
            (Path(p), ran)
            for p, ran in (run_unit(str(cache.root), name, parts, build) for parts, build in units)
        ]


def _check_reachable(address: str, timeout_s: float = 5.0) -> None:
    """Refuse a Ray ``--address`` whose host:port takes no TCP connection within ``timeout_s``.

    ``ray.init`` retries an unreachable head for minutes before it fails with a traceback; a
    plain connection says the same in seconds. ``auto`` (a cluster found on this machine) and an
    address without a port are left to Ray.
    """
    hostport = address.split("://", 1)[-1].rstrip("/")
    host, sep, port = hostport.rpartition(":")
    if address == "auto" or not sep or not port.isdigit():
        return
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=timeout_s):
            pass
    except OSError as err:
        raise ConfigError(
            f"--executor ray: cannot reach the Ray cluster at --address {address}: "
            f"{err.strerror or type(err).__name__} (is its head node running, and the port open?)"
        ) from None


@dataclass
class RayExecutor:
    """Map units over a Ray cluster.

    Args:
        address: ``None`` starts a local cluster (``num_cpus`` workers); ``"auto"`` or
            ``"ray://host:10001"`` joins an existing one (every node must see the output and data
            paths).
        num_cpus: workers of a local cluster.
        max_retries: retries of a unit whose worker process dies.
        fault_once: test hook: the first unit to start creates this file and kills its own worker
            process half-way through its build, once.
    """

    address: str | None = None
    num_cpus: int | None = None
    max_retries: int = 3
    fault_once: str | None = None
    name: str = "ray"

    def __post_init__(self) -> None:
        try:
            import ray
        except ImportError:
            raise ConfigError("--executor ray needs Ray: pip install 'dbl-harness[ray]'") from None
        if not ray.is_initialized():
            if self.address is not None:
                _check_reachable(self.address)
            kw: dict[str, Any] = {"include_dashboard": False, "log_to_driver": False}
            if self.address is None:
                kw["num_cpus"] = self.num_cpus
            else:
                kw["address"] = self.address
            try:
                ray.init(**kw)
            except (ConnectionError, TimeoutError, RuntimeError, ValueError) as err:
                where = self.address or "a local cluster"
                first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
                raise ConfigError(
                    f"--executor ray: cannot start or reach {where}: {first}"
                ) from None
        self._gpus = ray.cluster_resources().get("GPU", 0) > 0
        log.info("ray: %s", ray.cluster_resources())

    def describe(self) -> dict[str, Any]:
        """What ran the units, for ``run.json``: the cluster's address and CPU workers."""
        import ray

        res = ray.cluster_resources()
        return {
            "name": "ray",
            "address": self.address or "local",
            "workers": int(res.get("CPU", 0)),
            "gpus": int(res.get("GPU", 0)),
        }

    def map_units(
        self, cache: StageCache, name: str, units: list[Unit], gpu: bool = False
    ) -> list[tuple[Path, bool]]:
        """Build the missing units as Ray tasks (a GPU each when ``gpu`` and the cluster has one).

        Returns:
            (entry path, whether it was built now) per unit, in the units' order.
        """
        import ray

        out: list[tuple[Path, bool] | None] = [None] * len(units)
        todo = []
        for i, (parts, _) in enumerate(units):
            key = cache.key(name, *parts)
            if cache.is_done(name, key):  # finished shards are not even submitted
                out[i] = (cache.path(name, key), False)
            else:
                todo.append(i)
        task = ray.remote(_ray_unit).options(
            max_retries=self.max_retries, num_gpus=1 if (gpu and self._gpus) else 0
        )
        refs = [
            task.remote(str(cache.root), name, units[i][0], units[i][1], self.fault_once)
            for i in todo
        ]
        try:
            got = ray.get(refs)
        except ray.exceptions.RayTaskError as err:
            cause = getattr(err, "cause", None)
            if isinstance(cause, HarnessError):  # a worker's own error, as one line
                raise cause from None
            raise
        for i, (p, ran) in zip(todo, got, strict=True):
            out[i] = (Path(p), ran)
        return out  # type: ignore[return-value]


def _ray_unit(
    root: str, name: str, parts: tuple, build: Callable[[Path], dict | None], fault_once: str | None
) -> tuple[str, bool]:
    if fault_once and not os.path.exists(fault_once):

        def dying(tmp: Path) -> dict | None:
            (tmp / "partial").write_text("half-written")
            Path(fault_once).touch()
            os._exit(1)  # the worker process dies mid-unit; Ray retries the task

        return run_unit(root, name, parts, dying)
    return run_unit(root, name, parts, build)


def make_executor(
    kind: str, address: str | None = None, num_cpus: int | None = None
) -> LocalExecutor | RayExecutor:
    """The executor ``--executor`` names (``local`` or ``ray``).

    Raises:
        ConfigError: An unknown kind.
    """
    if kind == "local":
        return LocalExecutor()
    if kind == "ray":
        return RayExecutor(address=address, num_cpus=num_cpus)
    raise ConfigError(f"unknown executor {kind!r}; known: local, ray")
