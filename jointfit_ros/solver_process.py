"""The node's solver process: joint estimates solved off the executor thread.

Solving a window (:func:`~jointfit_core.estimator.solve_window`) takes about
0.3 ms for a ball joint and 0.4 ms for a hinge with rigid attachment, 2-3 ms
with skin attachment (the default: the soft-tissue part's finite differences).
On the executor thread, every
solve delays the marker frames that arrive meanwhile, and those delays set the
node's p99 latency (``bench/node_latency.py``). Python threads would not help:
the solve holds the GIL. So at an estimate tick the node sends the snapshots
of every joint's due window
(:meth:`~jointfit_core.estimator.OnlineJoint.solve_request`, about 2 kB each)
to one worker process in one message, the worker solves them one after the
other and answers them in one message, and the node installs the answers at
its next estimate tick (:meth:`~jointfit_core.estimator.OnlineJoint.install`
drops, joint by joint, answers made stale by a reset, freeze or new frames
solved meanwhile). One round trip per tick, not one per joint: with 12 joints
each estimate waits one tick, not 12 (``bench/solver_batch.py``). A solve that
raises comes back as that joint's error; the other joints of the batch are
solved. Both processes run the same function on the same numbers, so the
estimates equal the in-process ones bit for bit.

The worker starts with the first request (a node that never solves, e.g. one
that loaded a frozen calibration, never runs it: ~90 MB). It imports numpy,
scipy and jointfit_core, not rclpy. It ignores
SIGINT (Ctrl-C in a terminal reaches the whole process group; the node shuts
it down) and exits when its socket closes, so it never outlives the node, even
one that was killed. When the worker is gone or stops answering, the node
solves on its executor thread again and says so once in its log.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import fields
from multiprocessing.connection import Connection
from pathlib import Path

import numpy as np

from jointfit_core.errors import JointfitError
from jointfit_core.estimator import SolveRequest, SolveResult, solve_window

__all__ = ["Answer", "Batch", "SolverProcess", "serve", "solve_batch", "SOLVE_TIMEOUT_S"]

#: Seconds without an answer after which the worker is taken for hung, stopped, and solving moves back in-process.
SOLVE_TIMEOUT_S = 10.0

#: A batch of requests: ``(key, request)`` per joint (the key names the joint in the answers).
Batch = Sequence[tuple[str, SolveRequest]]
#: One joint's answer: ``(key, result or the error its solve raised)``.
Answer = tuple[str, SolveResult | JointfitError]


def solve_batch(batch: Batch) -> list[Answer]:
    """Solve each request of ``batch`` in turn (:func:`~jointfit_core.estimator.solve_window`): the worker's work.

    Parameters
    ----------
    batch : sequence of (str, SolveRequest)

    Returns
    -------
    list of (str, SolveResult or JointfitError)
        In the batch's order. A solve that raises gives that joint's error (a
        :class:`~jointfit_core.errors.JointfitError` as raised; any other
        exception, a bug, as a JointfitError that names it) and the other
        joints are still solved.
    """
    answers: list[Answer] = []
    for key, request in batch:
        answer: SolveResult | JointfitError
        try:
            answer = solve_window(request)
        except JointfitError as exc:
            answer = exc
        except Exception as exc:  # a bug: reported as this solve's failure, not a silent dead worker
            answer = JointfitError(f"solver process: {type(exc).__name__}: {exc}")
        answers.append((key, answer))
    return answers


class SolverProcess:
    """One worker process that solves a batch of windows at a time, with a non-blocking interface.

    Attributes
    ----------
    problem : str
        Why the worker is no longer used (empty while it is).
    """

    def __init__(self) -> None:
        self._proc: subprocess.Popen[bytes] | None = None  # started by the first submit()
        self._conn: Connection | None = None
        self._keys: tuple[str, ...] | None = None  # the joints of the batch being solved
        self._since = 0.0
        self.problem = ""

    def _start(self) -> Connection:
        """Start the worker (on the first request: a node that never solves, e.g. frozen, never pays for it)."""
        ours, theirs = socket.socketpair()
        env = dict(os.environ)
        # the worker imports this checkout of jointfit, whatever the caller's sys.path
        root = str(Path(__file__).resolve().parent.parent)
        env["PYTHONPATH"] = os.pathsep.join(p for p in (root, env.get("PYTHONPATH", "")) if p)
        code = "import sys; from jointfit_ros.solver_process import serve; serve(int(sys.argv[1]))"
        self._proc = subprocess.Popen(
            [sys.executable, "-c", code, str(theirs.fileno())],
            pass_fds=(theirs.fileno(),),
            stdin=subprocess.DEVNULL,
            env=env,
        )
        theirs.close()
        self._conn = Connection(ours.detach())
        return self._conn

    @property
    def started(self) -> bool:
        """Whether the worker process was started (by a first :meth:`submit`)."""
        return self._proc is not None

    @property
    def alive(self) -> bool:
        """Whether the worker is in use (started, not failed, not closed)."""
        return not self.problem

    @property
    def idle(self) -> bool:
        """Whether the worker can take a batch now (none is being solved)."""
        return self.alive and self._keys is None

    def submit(self, batch: Batch) -> bool:
        """Send ``batch`` in one message (each key names its request in the answers); False when busy or gone.

        Parameters
        ----------
        batch : sequence of (str, SolveRequest)
            One request per joint (distinct keys), at least one.

        Raises
        ------
        ValueError
            An empty batch, or a key given twice.
        """
        batch = list(batch)
        keys = tuple(key for key, _ in batch)
        if not keys or len(set(keys)) != len(keys):
            raise ValueError(f"a batch takes one request per key, at least one; got keys {list(keys)}")
        if not self.idle:
            return False
        try:
            conn = self._conn if self._conn is not None else self._start()
            conn.send(batch)
        except OSError as exc:
            self._fail(f"solver process unreachable ({exc})")
            return False
        self._keys, self._since = keys, time.monotonic()
        return True

    def ready(self, timeout: float = 0.0) -> bool:
        """Whether :meth:`collect` has the batch's answers (or the worker's end) to report; waits up to ``timeout`` s."""
        if not self.alive or self._keys is None or self._conn is None:
            return False
        try:
            return self._conn.poll(timeout)
        except OSError:
            return True  # collect() finds out what happened

    def collect(self) -> list[Answer]:
        """The batch's answers once they have arrived (without waiting), else none.

        Returns
        -------
        list of (str, SolveResult or JointfitError)
            ``(key, result or the error the solve raised)`` for every request
            of the batch, in its order; empty while it is being solved, and
            when the worker is gone (:attr:`problem` says why).
        """
        answers: list[Answer] = []
        if self._conn is None:
            return answers
        try:
            if self.alive and self._conn.poll(0):  # (also when idle: a worker that died is noticed)
                for key, answer in self._conn.recv():
                    if isinstance(answer, SolveResult):  # unpickled arrays are writable: make them read-only again
                        _read_only(answer.solution)
                        if answer.statistical is not None:
                            _read_only(answer.statistical)
                    answers.append((key, answer))
                self._keys = None
        except (EOFError, OSError) as exc:
            code = self._proc.poll() if self._proc is not None else None
            self._fail(f"solver process ended (exit code {code}; {exc or 'connection closed'})")
            return []
        if self._keys is not None and time.monotonic() - self._since > SOLVE_TIMEOUT_S:
            self._fail(f"solver process gave no answer in {SOLVE_TIMEOUT_S:g} s")
        return answers

    def _fail(self, why: str) -> None:
        """Give the worker up: it is gone or hung, so it is killed at once (no wait on the frames' thread)."""
        self.problem = why
        self._keys = None
        if self._conn is not None:
            self._conn.close()
        if self._proc is not None:
            if self._proc.poll() is None:
                self._proc.kill()
            self._proc.wait()

    def close(self, timeout: float = 2.0) -> None:
        """Stop the worker (closing its socket ends it; killed after ``timeout`` seconds)."""
        if not self.problem:
            self.problem = "closed"
        if self._conn is not None:
            self._conn.close()
        if self._proc is None:
            return
        try:
            self._proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait()


def _read_only(solution: object) -> None:
    """Make the array fields of an unpickled solution read-only, as the estimator's own (in place: no copies)."""
    for f in fields(solution):  # type: ignore[arg-type]
        value = getattr(solution, f.name)
        if isinstance(value, np.ndarray):
            value.setflags(write=False)


def serve(fd: int) -> None:
    """The worker's loop: receive a batch of ``(key, SolveRequest)``, answer it in one message (:func:`solve_batch`).

    Parameters
    ----------
    fd : int
        The worker's end of the socket pair.
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _idle_priority()
    conn = Connection(fd)
    while True:
        try:
            batch = conn.recv()
        except (EOFError, OSError):
            return  # the node closed the socket, or is gone
        try:
            conn.send(solve_batch(batch))
        except OSError:
            return


def _idle_priority() -> None:
    """Run the worker only on otherwise idle CPU time (Linux SCHED_IDLE; else the lowest nice value).

    At normal priority the woken worker preempts the node on the same core and a
    solve delays the frames as much as solving in the node did.
    """
    try:
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))  # type: ignore[attr-defined,unused-ignore]
    except (AttributeError, OSError):
        try:
            os.nice(19)
        except OSError:
            pass
