"""One layer of an exported stack served by a process of its own, and the messages between it and the driver.

The driver (`layered.deploy`) sends a `Request` with what the layer sees whenever the stack's rules
have the layer decide; the layer's process answers with a `Reply` holding its policy's output. Both
carry the protocol version, the episode and the base step the decision is for, so that a late answer
is matched to its decision and an answer of another protocol is refused. Messages travel over a
`multiprocessing` pipe (pickled; about 50 µs there and back). A `Link` delays each message by a
seeded random amount, so that a network between the layers can be emulated on one machine; a `Fault`
makes the process die or stall at a chosen decision, to test what the driver does then.
"""

from __future__ import annotations

import json
import multiprocessing
import os
import re
import queue
import signal
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any, Protocol

import numpy as np

PROTOCOL = 1  # of the messages below; a process refuses a request of another version, the driver a reply
WARMUP_CALLS = 20  # untimed calls before the process says it is ready: TorchScript optimises over its first calls
UNITS = {"us": 1e-6, "µs": 1e-6, "ms": 1e-3, "s": 1.0}


class LayerFault(RuntimeError):
    """A layer's process died, stalled or broke the protocol."""


@dataclass(frozen=True)
class Request:
    """What layer `layer` sees before its decision for base `step` of `episode`, sent at `sent` (the
    driver's wall clock, seconds since the epoch)."""

    version: int
    layer: str
    episode: int
    step: int
    view: np.ndarray
    sent: float = 0.0


@dataclass(frozen=True)
class Reply:
    """A layer's output for its decision at base `step` of `episode`, how long its policy took, and when
    (the layer's wall clock) the request reached it and the reply left."""

    version: int
    layer: str
    episode: int
    step: int
    output: np.ndarray
    compute_s: float
    received: float = 0.0
    replied: float = 0.0


@dataclass(frozen=True)
class Refusal:
    """A process's answer to a message it cannot take, after which it exits."""

    version: int
    layer: str
    reason: str


@dataclass(frozen=True)
class Link:
    """A one-way delay of `mean_s` ± `jitter_s` (uniform) on each message to and from a layer."""

    mean_s: float = 0.0
    jitter_s: float = 0.0

    @classmethod
    def parse(cls, text: str) -> Link:
        """`5ms`, `5ms±2ms` or `5ms+-2ms` (units us, ms, s)."""
        parts = re.split(r"±|\+-", text.strip())
        if not 1 <= len(parts) <= 2:
            raise ValueError(f"link delay {text!r}: expected e.g. 5ms or 5ms±2ms")
        seconds = [_seconds(part, text) for part in parts]
        link = cls(seconds[0], seconds[1] if len(seconds) == 2 else 0.0)
        if link.jitter_s > link.mean_s:
            raise ValueError(f"link delay {text!r}: the jitter is larger than the mean, so a delay could be negative")
        return link

    def sample(self, rng: np.random.Generator) -> float:
        """One message's delay in seconds."""
        return self.mean_s + (rng.uniform(-self.jitter_s, self.jitter_s) if self.jitter_s else 0.0)

    def __str__(self) -> str:
        return f"{self.mean_s * 1e3:g}ms" + (f"±{self.jitter_s * 1e3:g}ms" if self.jitter_s else "")


def _seconds(text: str, whole: str) -> float:
    match = re.fullmatch(r"\s*([0-9]*\.?[0-9]+)\s*(us|µs|ms|s)\s*", text)
    if match is None:
        raise ValueError(f"link delay {whole!r}: {text.strip()!r} is not a duration such as 5ms, 200us or 0.1s")
    return float(match.group(1)) * UNITS[match.group(2)]


@dataclass(frozen=True)
class Fault:
    """Make the layer's process `die` (exit at once) or `stall` (stop answering) at its `decision`-th request."""

    kind: str
    decision: int

    @classmethod
    def parse(cls, text: str) -> Fault:
        """`die@100` or `stall@100` (the 100th request, counted from 1 over the whole deployment)."""
        match = re.fullmatch(r"(die|stall)@([1-9][0-9]*)", text.strip())
        if match is None:
            raise ValueError(f"fault {text!r}: expected die@N or stall@N (N a request, counted from 1)")
        return cls(match.group(1), int(match.group(2)))


class Server:
    """A layer's policy answering requests, with the fault it is to inject."""

    def __init__(self, directory: str | Path, backend: str, name: str, fault: Fault | None) -> None:
        import torch

        from layered.runtime import load_policy

        torch.set_num_threads(1)
        self.name, self.fault = name, fault
        self.policy = load_policy(directory, name, backend)
        dims = int(json.loads((Path(directory) / "stack.json").read_text())["observation_dims"][name])
        for _ in range(WARMUP_CALLS):
            self.policy(np.zeros(dims, np.float32))
        self.count = 0

    def answer(self, request: object) -> Reply | Refusal | None:
        """The reply to `request`; a refusal for a message of another protocol; None once stalled."""
        if not isinstance(request, Request) or request.version != PROTOCOL:
            version = getattr(request, "version", None)
            return Refusal(PROTOCOL, self.name, f"a request of protocol version {version!r}; "
                                                f"this layer speaks version {PROTOCOL}")
        self.count += 1
        if self.fault is not None and self.count >= self.fault.decision:
            if self.fault.kind == "die":
                os._exit(1)
            return None
        received = time.time()
        start = time.perf_counter()
        output = np.asarray(self.policy(request.view), np.float32)
        compute = time.perf_counter() - start
        return Reply(PROTOCOL, self.name, request.episode, request.step, output, compute, received, time.time())


def check_reply(name: str, message: object) -> Reply:
    """A layer's message as a reply of this protocol; anything else is a fault."""
    if isinstance(message, Refusal):
        raise LayerFault(f"layer {name!r} refused {message.reason}")
    if not isinstance(message, Reply) or message.version != PROTOCOL:
        version = getattr(message, "version", None)
        raise LayerFault(f"layer {name!r} sent a message of protocol version {version!r}; "
                         f"this driver speaks version {PROTOCOL}")
    return message


def serve(connection: Connection, directory: str, backend: str, name: str, link: Link, fault: Fault | None,
          seed: int) -> None:
    """The layer process: load the policy, say it is ready, then answer requests until the driver hangs up."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the driver's to handle: it stops this process
    server = Server(directory, backend, name, fault)
    ready = ("ready", PROTOCOL, name, os.getpid())
    if link.mean_s:
        _serve_over_link(connection, server, link, np.random.default_rng(seed), ready)
        return
    connection.send(ready)
    while (request := _receive_or_none(connection)) is not None:
        reply = server.answer(request)
        if reply is None:
            while _receive_or_none(connection) is not None:  # stalled: alive, answering nothing
                pass
            return
        connection.send(reply)
        if isinstance(reply, Refusal):
            return


def _receive_or_none(connection: Connection) -> object:
    """The next message; None when the driver hangs up or is gone."""
    try:
        return connection.recv()
    except (EOFError, OSError):
        return None


def _serve_over_link(connection: Connection, server: Server, link: Link, rng: np.random.Generator,
                     ready: object) -> None:
    """Answer as `serve` does, each message held for a sample of the link's delay on its way in and out.
    A link delays messages without holding up the ones behind them: a reader thread stamps each
    request's arrival, and a writer thread sends each reply at its own release time. Says `ready` once both
    run, so that the driver's clock does not start while they are still starting (on a busy machine the
    first answer then came late enough to be taken for a stall)."""
    inbox: queue.Queue[tuple[float, object]] = queue.Queue()
    outbox: queue.Queue[tuple[float, object] | None] = queue.Queue()

    def read() -> None:
        while True:
            message = _receive_or_none(connection)
            inbox.put((time.monotonic(), message))
            if message is None:
                return

    def write() -> None:
        while (item := outbox.get()) is not None:
            release, reply = item
            time.sleep(max(0.0, release - time.monotonic()))
            try:
                connection.send(reply)
            except OSError:
                return

    threading.Thread(target=read, daemon=True).start()
    writer = threading.Thread(target=write, daemon=True)
    writer.start()
    connection.send(ready)
    stalled = False
    while (item := inbox.get())[1] is not None:
        arrival, request = item
        if stalled:
            continue
        time.sleep(max(0.0, arrival + link.sample(rng) - time.monotonic()))
        reply = server.answer(request)
        stalled = reply is None
        if reply is not None:
            outbox.put((time.monotonic() + link.sample(rng), reply))
        if isinstance(reply, Refusal):
            break
    outbox.put(None)
    writer.join(5.0)


class LayerEnd(Protocol):
    """The driver's end of a layer, whatever carries its messages (a process's pipe, a Ray actor)."""

    name: str
    pid: int | None
    waitable: Any  # what `multiprocessing.connection.wait` can wait on for its answers, or None

    def wait_ready(self, timeout_s: float) -> None: ...
    def send(self, request: Request) -> None: ...
    def receive(self, timeout_s: float) -> Reply | None: ...
    def abandon(self) -> None: ...
    def close(self) -> None: ...


@contextmanager
def _sigint_ignored() -> Iterator[None]:
    """SIGINT ignored within the block (in the main thread, where Python can set handlers), so that a process
    started in it inherits that across its exec and never raises KeyboardInterrupt, even before `serve` runs."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    before = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, before)


class LayerProcess:
    """The driver's end of one layer's process: start it, send requests, take replies, stop it."""

    def __init__(self, name: str, directory: Path, backend: str, link: Link = Link(), fault: Fault | None = None,
                 seed: int = 0) -> None:
        context = multiprocessing.get_context("spawn")  # a fresh interpreter: no forked torch or MuJoCo state
        self.name = name
        self.connection, child = context.Pipe()
        self.process = context.Process(target=serve, args=(child, str(directory), backend, name, link, fault, seed),
                                       name=f"layered-{name}", daemon=True)
        with _sigint_ignored():  # from its first instruction: a Ctrl-C while it imports is the driver's too
            self.process.start()
        child.close()  # the child holds the only other end: its death is an end of file here at once
        self.pid: int | None = self.process.pid
        self.waitable: Any = self.connection

    def wait_ready(self, timeout_s: float) -> None:
        """Block until the process has loaded its policy; a process that fails to is a fault."""
        if not self.connection.poll(timeout_s):
            raise LayerFault(f"layer {self.name!r} did not start within {timeout_s:g} s")
        message = self._receive()
        if not (isinstance(message, tuple) and message[:2] == ("ready", PROTOCOL)):
            raise LayerFault(f"layer {self.name!r} started with an unexpected message {message!r}")

    def send(self, request: Request) -> None:
        """Send a request; a process that is gone is a fault."""
        try:
            self.connection.send(request)
        except (BrokenPipeError, ConnectionResetError, OSError):
            raise LayerFault(f"layer {self.name!r} (pid {self.pid}) is gone: {self._how_it_ended()}") from None

    def receive(self, timeout_s: float) -> Reply | None:
        """The next reply within `timeout_s` (0: only one already here), or None."""
        if not self.connection.poll(max(timeout_s, 0.0)):
            return None
        return check_reply(self.name, self._receive())

    def _receive(self) -> object:
        try:
            return self.connection.recv()
        except (EOFError, OSError):
            raise LayerFault(f"layer {self.name!r} (pid {self.pid}) died: {self._how_it_ended()}") from None

    def _how_it_ended(self) -> str:
        self.process.join(0.5)
        code = self.process.exitcode
        if code is None:
            return "its connection closed"
        return f"killed by signal {-code}" if code < 0 else f"exit status {code}"

    def abandon(self) -> None:
        """Stop a faulted layer's process at once, without waiting for it to end (the driver's clock goes on; `close`
        collects it later)."""
        if self.process.is_alive():
            self.process.kill()

    def close(self) -> None:
        """Ask the process to exit; stop it if it does not within a second. Idempotent."""
        try:
            self.connection.send(None)
        except (BrokenPipeError, ConnectionResetError, OSError):
            pass
        self.process.join(1.0)
        if self.process.is_alive():
            self.process.kill()
            self.process.join()
        self.connection.close()
