"""The node's solver process: joint estimates solved off the executor thread.

Solving a window (:func:`~jointfit_core.estimator.solve_window`) takes about
0.3 ms for a ball joint and 0.6 ms for a hinge. On the executor thread, every
solve delays the marker frames that arrive meanwhile, and those delays set the
node's p99 latency (``bench/node_latency.py``). Python threads would not help:
the solve holds the GIL. So the node sends each due window's snapshot
(:meth:`~jointfit_core.estimator.OnlineJoint.solve_request`, about 2 kB) to
one worker process and installs the answer at its next estimate tick
(:meth:`~jointfit_core.estimator.OnlineJoint.install` drops answers made stale
by a reset, freeze or new frames solved meanwhile). Both processes run the
same function on the same numbers, so the estimates equal the in-process ones
bit for bit.

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
from dataclasses import replace
from multiprocessing.connection import Connection
from pathlib import Path

from jointfit_core.errors import JointfitError
from jointfit_core.estimator import SolveRequest, SolveResult, solve_window

__all__ = ["SolverProcess", "serve", "SOLVE_TIMEOUT_S"]

#: Seconds without an answer after which the worker is taken for hung, stopped, and solving moves back in-process.
SOLVE_TIMEOUT_S = 10.0


class SolverProcess:
    """One worker process that solves windows one at a time, with a non-blocking interface.

    Attributes
    ----------
    problem : str
        Why the worker is no longer used (empty while it is).
    """

    def __init__(self) -> None:
        self._proc: subprocess.Popen[bytes] | None = None  # started by the first submit()
        self._conn: Connection | None = None
        self._key: str | None = None  # the joint whose window is being solved
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
        """Whether the worker can take a request now."""
        return self.alive and self._key is None

    def submit(self, key: str, request: SolveRequest) -> bool:
        """Send ``request`` (``key`` names it in the answer); False when busy or gone."""
        if not self.idle:
            return False
        try:
            conn = self._conn if self._conn is not None else self._start()
            conn.send((key, request))
        except OSError as exc:
            self._fail(f"solver process unreachable ({exc})")
            return False
        self._key, self._since = key, time.monotonic()
        return True

    def ready(self, timeout: float = 0.0) -> bool:
        """Whether :meth:`collect` has an answer (or the worker's end) to report; waits up to ``timeout`` s."""
        if not self.alive or self._key is None or self._conn is None:
            return False
        try:
            return self._conn.poll(timeout)
        except OSError:
            return True  # collect() finds out what happened

    def collect(self) -> list[tuple[str, SolveResult | JointfitError]]:
        """Answers that have arrived (without waiting): ``(key, result or the error the solve raised)``."""
        answers: list[tuple[str, SolveResult | JointfitError]] = []
        if self._conn is None:
            return answers
        try:
            while self.alive and self._conn.poll(0):
                key, answer = self._conn.recv()
                if isinstance(answer, SolveResult):  # unpickled arrays are writable: make them read-only again
                    answer = replace(answer, solution=replace(answer.solution))
                answers.append((key, answer))
                self._key = None
        except (EOFError, OSError) as exc:
            code = self._proc.poll() if self._proc is not None else None
            self._fail(f"solver process ended (exit code {code}; {exc or 'connection closed'})")
        if self._key is not None and time.monotonic() - self._since > SOLVE_TIMEOUT_S:
            self._fail(f"solver process gave no answer in {SOLVE_TIMEOUT_S:g} s")
        return answers

    def _fail(self, why: str) -> None:
        """Give the worker up: it is gone or hung, so it is killed at once (no wait on the frames' thread)."""
        self.problem = why
        self._key = None
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


def serve(fd: int) -> None:
    """The worker's loop: receive ``(key, SolveRequest)``, answer ``(key, SolveResult or JointfitError)``.

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
            key, request = conn.recv()
        except (EOFError, OSError):
            return  # the node closed the socket, or is gone
        answer: SolveResult | JointfitError
        try:
            answer = solve_window(request)
        except JointfitError as exc:
            answer = exc
        except Exception as exc:  # a bug: reported as this solve's failure, not a silent dead worker
            answer = JointfitError(f"solver process: {type(exc).__name__}: {exc}")
        try:
            conn.send((key, answer))
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
