"""Where GL work runs: a thread with its own context (:class:`GLWorker`) or a child process (:class:`ProcessWorker`).

:class:`GLWorker` is the one thread of a process (or of one live server / client inside a process) that runs GL.
moderngl contexts are current on one thread, so every GL call -- rendering, encoding, decoding into textures --
goes through :meth:`GLWorker.call` from the asyncio loop, one job at a time in submission order, and the event loop
(pose I/O) never waits on the GPU. The worker makes its own headless EGL context (:func:`quadcast.render.gl.
create_context`), so several workers (a server and a client in one test process) and a main-thread
:func:`quadcast.render.gl.gl_context` coexist. moderngl holds the GIL during GL calls, though, so a thread still
stalls its process's event loop while it renders (up to ~350 ms at 1920x1080 on llvmpipe): the live client uses
it (its pose I/O matters less), the live server uses :class:`ProcessWorker`.

:class:`ProcessWorker` is a child process (``spawn`` start method, so nothing GL is inherited) that builds one
handler object from a picklable factory and runs its methods on request, in order, over a pipe. The event loop
only pickles small requests; a reader thread per worker waits on the pipe and hands the replies to the loop. A
worker that dies (killed, crashed) fails its pending and later calls with :class:`WorkerDied`; workers are daemon
processes that also die with their parent (:func:`die_with_parent`) or when their pipe closes.
"""
from __future__ import annotations

import asyncio
import collections
import concurrent.futures
import ctypes
import multiprocessing
import os
import signal
import sys
import threading
import traceback
from typing import Any, Callable

import moderngl

from quadcast.render.gl import create_context

__all__ = ["GLWorker", "ProcessWorker", "WorkerError", "WorkerDied", "die_with_parent"]


class GLWorker:
    """A thread owning a private headless GL context; runs submitted jobs one at a time, in order.

    ``await worker.call(fn, *args)`` runs ``fn(*args)`` on the thread and returns its result (or raises its
    exception). :attr:`ctx` is the thread's context: pass it to everything that makes GL objects
    (``DeferredRenderer(scene, worker.ctx)``, ``make_client(name, config, worker.ctx)``) and only touch those
    objects inside jobs. :meth:`close` finishes the queued jobs and stops the thread.
    """

    def __init__(self, name: str = "gl") -> None:
        self._jobs: "collections.deque[tuple | None]" = collections.deque()
        self._wake = threading.Condition()
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self.ctx: moderngl.Context | None = None
        self._closed = False
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()
        self._ready.wait()
        if self._error is not None:
            raise self._error

    def _run(self) -> None:
        try:
            self.ctx = create_context()
        except BaseException as exc:
            self._error = exc
            self._ready.set()
            return
        self._ready.set()
        while True:
            with self._wake:
                while not self._jobs:
                    self._wake.wait()
                job = self._jobs.popleft()
            if job is None:
                break
            future, fn, args = job
            if not future.set_running_or_notify_cancel():
                continue
            try:
                future.set_result(fn(*args))
            except BaseException as exc:  # handed to the caller
                future.set_exception(exc)
        self.ctx.release()

    def submit(self, fn: Callable[..., Any], *args) -> concurrent.futures.Future:
        """Queue ``fn(*args)``; returns a future of its result."""
        if self._closed:
            raise RuntimeError("GLWorker.submit: the worker is closed")
        future: concurrent.futures.Future = concurrent.futures.Future()
        with self._wake:
            self._jobs.append((future, fn, args))
            self._wake.notify()
        return future

    async def call(self, fn: Callable[..., Any], *args) -> Any:
        """Run ``fn(*args)`` on the GL thread without blocking the event loop."""
        return await asyncio.wrap_future(self.submit(fn, *args))

    def close(self, timeout: float = 30.0) -> None:
        """Run what is queued, then stop the thread and release the context."""
        if self._closed:
            return
        self._closed = True
        with self._wake:
            self._jobs.append(None)
            self._wake.notify()
        self._thread.join(timeout)


class WorkerError(RuntimeError):
    """A call on a :class:`ProcessWorker` raised in the child; the message names the child's exception."""


class WorkerDied(RuntimeError):
    """A :class:`ProcessWorker`'s process ended (killed, crashed, or it failed to start)."""


def die_with_parent(sig: int = signal.SIGKILL) -> None:
    """Linux: the calling process gets ``sig`` when its parent dies (also usable as a ``preexec_fn``)."""
    if sys.platform.startswith("linux"):
        try:
            ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, sig)   # PR_SET_PDEATHSIG
        except OSError:
            pass


def _describe(exc: BaseException) -> tuple[str, str]:
    return f"{type(exc).__name__}: {exc}", "".join(traceback.format_exception(exc))[-4000:]


def _process_main(conn, factory: Callable[..., Any], args: tuple) -> None:
    """The body of a :class:`ProcessWorker`'s child: build the handler, then serve ``(method, args)`` requests."""
    die_with_parent()
    try:
        handler = factory(*args)
    except BaseException as exc:  # noqa: BLE001 -- reported to the parent
        conn.send(("error", *_describe(exc)))
        return
    conn.send(("ok", os.getpid()))
    try:
        while True:
            try:
                request = conn.recv()
            except (EOFError, OSError):
                break                      # the parent is gone
            if request is None:
                break
            name, call_args = request
            try:
                reply = ("ok", getattr(handler, name)(*call_args))
            except Exception as exc:  # noqa: BLE001 -- reported to the parent
                reply = ("error", *_describe(exc))
            conn.send(reply)
    finally:
        close = getattr(handler, "close", None)
        if close is not None:
            close()


class ProcessWorker:
    """A child process (``spawn``) holding ``factory(*args)``; ``await worker.call("method", *args)`` runs
    ``handler.method(*args)`` there, one call at a time in submission order, and returns its (pickled) result.

    ``await worker.start(timeout)`` waits until the handler is built (its own GL context, renderer, ...) and
    raises :class:`WorkerError` if building failed or :class:`WorkerDied` if the process ended first. A call
    that raises in the child raises :class:`WorkerError` here (the worker goes on); if the process dies, every
    pending and later call raises :class:`WorkerDied` and :attr:`died` is set. :meth:`close` asks the child to
    close its handler and exit, and terminates (then kills) it if it does not within ``timeout``.
    """

    def __init__(self, factory: Callable[..., Any], args: tuple = (), name: str = "worker") -> None:
        ctx = multiprocessing.get_context("spawn")
        self.name = name
        self._conn, child_conn = ctx.Pipe(duplex=True)
        self.process = ctx.Process(target=_process_main, args=(child_conn, factory, args), name=name, daemon=True)
        self._pending: collections.deque[concurrent.futures.Future] = collections.deque()
        self._lock = threading.Lock()
        self._proc_lock = threading.Lock()     # join / exitcode from one thread at a time
        self._dead: str | None = None
        self._closing = False
        self._loop: asyncio.AbstractEventLoop | None = None
        self.died: asyncio.Event | None = None
        self.pid: int | None = None
        self._ready: concurrent.futures.Future = concurrent.futures.Future()
        self._pending.append(self._ready)       # the child's first message answers "are you built?"
        self.process.start()
        child_conn.close()
        self._reader = threading.Thread(target=self._read, name=f"{name}-pipe", daemon=True)
        self._reader.start()

    def _read(self) -> None:
        """Reader thread: hand each reply to the oldest pending call; on EOF fail them all."""
        while True:
            try:
                reply = self._conn.recv()
            except (EOFError, OSError):
                break
            with self._lock:
                future = self._pending.popleft() if self._pending else None
            if future is None or future.cancelled():
                continue                   # nobody waits for this reply any more (its session was cancelled)
            try:
                if reply[0] == "ok":
                    future.set_result(reply[1])
                else:
                    exc = WorkerError(reply[1])
                    exc.child_traceback = reply[2]
                    future.set_exception(exc)
            except concurrent.futures.InvalidStateError:
                pass                       # cancelled meanwhile
        with self._proc_lock:
            self.process.join(5.0)
            code = self.process.exitcode
        how = (f"was killed by signal {-code}" if code is not None and code < 0 else
               f"exited with code {code}" if code is not None else "stopped answering")
        with self._lock:
            self._dead = f"{self.name}: worker process {self.process.pid} {how}"
            pending, self._pending = list(self._pending), collections.deque()
        for future in pending:
            if not future.done():
                future.set_exception(WorkerDied(self._dead))
        if self._loop is not None and self.died is not None:
            try:
                self._loop.call_soon_threadsafe(self.died.set)
            except RuntimeError:            # the loop is closed
                pass

    @property
    def alive(self) -> bool:
        return self._dead is None

    @property
    def death(self) -> str | None:
        """Why the process ended (None while it runs)."""
        return self._dead

    async def start(self, timeout: float = 60.0) -> int:
        """Wait for the handler to be built; returns the child's pid."""
        self._loop = asyncio.get_running_loop()
        self.died = asyncio.Event()
        if self._dead is not None:
            self.died.set()
        try:
            self.pid = await asyncio.wait_for(asyncio.wrap_future(self._ready), timeout)
        except asyncio.TimeoutError:
            raise WorkerDied(f"{self.name}: worker process {self.process.pid} not ready within {timeout:g} s") from None
        return self.pid

    def submit(self, name: str, *args) -> concurrent.futures.Future:
        """Send one request; returns a future of its reply."""
        future: concurrent.futures.Future = concurrent.futures.Future()
        with self._lock:
            if self._dead is not None:
                raise WorkerDied(self._dead)
            if self._closing:
                raise RuntimeError(f"{self.name}: the worker is closed")
            self._pending.append(future)
            try:
                self._conn.send((name, args))   # requests are small: the pipe takes them at once
            except (OSError, ValueError) as exc:
                self._pending.remove(future)
                raise WorkerDied(f"{self.name}: worker process {self.process.pid} unreachable ({exc})") from None
        return future

    async def call(self, name: str, *args) -> Any:
        """Run ``handler.name(*args)`` in the child without blocking the event loop."""
        return await asyncio.wrap_future(self.submit(name, *args))

    def close(self, timeout: float = 10.0) -> None:
        """Blocking: ask the child to exit after its queued calls, then terminate / kill it; reaps the process."""
        with self._lock:
            already, self._closing = self._closing, True
            if not already and self._dead is None:
                try:
                    self._conn.send(None)
                except (OSError, ValueError):
                    pass
        with self._proc_lock:
            self.process.join(timeout)
            if self.process.is_alive():
                self.process.terminate()
                self.process.join(2.0)
            if self.process.is_alive():
                self.process.kill()
                self.process.join(2.0)
        self._reader.join(timeout=5.0)
        self._conn.close()
