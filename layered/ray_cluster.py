"""Joining a Ray cluster (or starting a local one), for the sweep's tasks and the deployment's layers."""

from __future__ import annotations

import logging
from types import ModuleType


def start_ray(address: str | None = None) -> ModuleType:
    """The `ray` module, connected to the cluster at `address` (default: a local one, started here)."""
    try:
        import ray
    except ImportError:
        raise RuntimeError("Ray needs the optional extra: pip install -e '.[ray]' in the checkout") from None
    ray.init(address=address, include_dashboard=False, log_to_driver=False, ignore_reinit_error=True,
             logging_level=logging.ERROR,  # Ray's own start-up notices would interleave with the command's lines
             runtime_env={"env_vars": {"OMP_NUM_THREADS": "1"}})
    return ray
