"""One layer of an exported stack served by a Ray actor, which may sit on another machine of a Ray cluster.

The driver's end has `LayerProcess`'s interface, so the deployment runs the same over either
transport. The actor is given the bytes of its policy file and of `stack.json` (no shared file
system is needed), and answers requests one at a time, in order, through the same `Server`.
"""

from __future__ import annotations

import os
import tempfile
import time
from collections import deque
from functools import cache
from pathlib import Path
from typing import Any

from layered.layer_process import Fault, LayerFault, Link, Reply, Request, Server, check_reply


class _Served:
    """The actor: a `Server` over the files it was given."""

    def __init__(self, files: dict[str, bytes], backend: str, name: str, fault: Fault | None) -> None:
        self.folder = tempfile.mkdtemp(prefix=f"layered-{name}-")
        for file, data in files.items():
            (Path(self.folder) / file).write_bytes(data)
        self.server = Server(self.folder, backend, name, fault)

    def pid(self) -> int:
        return os.getpid()

    def answer(self, request: Request) -> Any:
        reply = self.server.answer(request)
        while reply is None:  # stalled: it answers nothing until the driver stops it
            time.sleep(3600)
        return reply


@cache
def _actor_class() -> Any:
    import ray

    return ray.remote(num_cpus=0)(_Served)  # a layer mostly waits: it takes no CPU of the cluster's count


class RayLayer:
    """The driver's end of one layer's Ray actor: start it, send requests, take replies, stop it."""

    def __init__(self, name: str, directory: Path, backend: str, link: Link, fault: Fault | None, seed: int) -> None:
        """`link` and `seed` are unused: a cluster's network delays are real (`deploy` refuses emulated links
        with Ray actors)."""
        suffix = {"torchscript": ".pt", "onnx": ".onnx"}[backend]
        files = {file: (directory / file).read_bytes() for file in (f"{name}{suffix}", "stack.json")}
        self.name = name
        self.actor = _actor_class().remote(files, backend, name, fault)
        self.replies: deque[Any] = deque()  # object refs of the requests sent, oldest first
        self.pid: int | None = None
        self.waitable: Any = None  # Ray's object refs are waited on by `ray.wait`: the driver polls

    def wait_ready(self, timeout_s: float) -> None:
        """Block until the actor has loaded its policy; one that fails to is a fault."""
        import ray

        ref = self.actor.pid.remote()
        ready, _ = ray.wait([ref], timeout=timeout_s)
        if not ready:
            raise LayerFault(f"layer {self.name!r} did not start within {timeout_s:g} s")
        self.pid = self._get(ref)

    def send(self, request: Request) -> None:
        self.replies.append(self.actor.answer.remote(request))

    def receive(self, timeout_s: float) -> Reply | None:
        """The next reply within `timeout_s` (0: only one already here), or None."""
        import ray

        if not self.replies:
            return None
        ready, _ = ray.wait([self.replies[0]], timeout=max(timeout_s, 0.0))
        if not ready:
            return None
        return check_reply(self.name, self._get(self.replies.popleft()))

    def _get(self, ref: Any) -> Any:
        import ray

        try:
            return ray.get(ref)
        except ray.exceptions.RayError as e:
            raise LayerFault(f"layer {self.name!r} (Ray actor, pid {self.pid}) died: "
                             f"{str(e).strip().splitlines()[0]}") from None

    def abandon(self) -> None:
        """Stop a faulted layer's actor (Ray does not wait for it)."""
        self.close()

    def close(self) -> None:
        """Stop the actor. Idempotent."""
        import ray

        ray.kill(self.actor)
