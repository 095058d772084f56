"""Solving a window elsewhere: OnlineJoint.solve_request / solve_window / install, and the node's solver process.

The node sends each due window to a worker process (jointfit_ros.solver_process)
so that solves do not delay the frames. The answer must equal the in-process
estimate bit for bit, stale answers (a reset, freeze, new sign convention, or
a newer estimate installed meanwhile) must be dropped, errors must arrive as
the estimator's own exceptions, and a worker that dies must be noticed.
"""

from __future__ import annotations

import dataclasses
import subprocess
import time

import numpy as np
import pytest
from numpy.typing import NDArray

from jointfit_core.errors import JointfitError, NotIdentifiableError
from jointfit_core.estimator import OnlineJoint, SolveRequest, SolveResult, solve_window
from jointfit_core.synthetic import two_segment_motion
from jointfit_ros.solver_process import SolverProcess

FloatArray = NDArray[np.float64]


def _joint(kind: str, frames: int = 1500, seed: int = 5) -> tuple[OnlineJoint, FloatArray, FloatArray]:
    """An estimator fed ``frames`` frames of a synthetic rig (0.5 mm noise), and the next 200 frames."""
    rng = np.random.default_rng(seed)
    m = two_segment_motion(rng, kind=kind)
    p, c = m.markers_at(np.arange(frames + 200) / 100.0)
    p = p + rng.normal(0.0, 0.5, p.shape)
    c = c + rng.normal(0.0, 0.5, c.shape)
    est = OnlineJoint(kind, 1000)
    est.update_many(p[:frames], c[:frames])
    return est, p[frames:], c[frames:]


def _fields(sol: object) -> dict[str, object]:
    return {f.name: getattr(sol, f.name) for f in dataclasses.fields(sol)}  # type: ignore[arg-type]


def _assert_identical(a: object, b: object) -> None:
    fa, fb = _fields(a), _fields(b)
    assert fa.keys() == fb.keys()
    for k, v in fa.items():
        if isinstance(v, np.ndarray):
            np.testing.assert_array_equal(v, fb[k], err_msg=k)
        else:
            assert v == fb[k] or (v != v and fb[k] != fb[k]), k  # NaN equals NaN here


@pytest.mark.parametrize("kind", ["ball", "hinge"])
def test_request_solve_install_is_estimate(kind: str) -> None:
    est, _, _ = _joint(kind)
    twin, _, _ = _joint(kind)
    request = est.solve_request()
    assert request is not None
    assert est.install(solve_window(request))
    sol = twin.estimate()
    _assert_identical(est.solution, sol)
    assert est.noise_std == twin.noise_std and est.serial_inflation == twin.serial_inflation
    assert est.solve_request() is None  # current: nothing to solve until a frame enters


@pytest.mark.parametrize("change", ["reset", "freeze", "sign", "newer", "frames"])
def test_stale_answers_are_dropped(change: str) -> None:
    est, p, c = _joint("hinge")
    request = est.solve_request()
    assert request is not None
    answer = solve_window(request)
    if change == "reset":
        est.reset()
    elif change == "freeze":
        frozen = est.freeze()
    elif change == "sign":
        est.set_reference_direction(-answer.solution.direction_parent)  # type: ignore[union-attr]
    elif change in ("newer", "frames"):
        est.update_many(p, c)
        if change == "newer":
            newer = est.estimate()  # e.g. the save service solves in-process meanwhile
    installed = est.install(answer)
    if change == "frames":
        # an answer older than the frames is still the newest estimate: installed, and still stale
        assert installed and est.solution is answer.solution
        assert est.solve_request() is not None
        return
    assert not installed
    if change == "reset":
        assert est.solution is None
    elif change == "freeze":
        assert est.solution is frozen
    elif change == "newer":
        assert est.solution is newer
    else:
        assert est.solution is None and est.solve_request() is not None


@pytest.fixture
def solver() -> SolverProcess:
    sp = SolverProcess()
    yield sp  # type: ignore[misc]
    sp.close()


def _answer(sp: SolverProcess, timeout: float = 30.0) -> list[tuple[str, SolveResult | JointfitError]]:
    """Wait for answers (the first one waits for the worker's imports)."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        answers = sp.collect()
        if answers or not sp.alive:
            return answers
        time.sleep(0.01)
    raise AssertionError("no answer from the solver process")


def test_solver_process_equals_in_process(solver: SolverProcess) -> None:
    for kind in ("ball", "hinge"):
        est, _, _ = _joint(kind, seed=7)
        request = est.solve_request()
        assert request is not None
        assert solver.idle and solver.submit(kind, request)
        assert not solver.idle and not solver.submit(kind, request)  # one at a time
        ((key, answer),) = _answer(solver)
        assert key == kind and isinstance(answer, SolveResult) and solver.idle
        _assert_identical(answer.solution, solve_window(request).solution)
        for v in _fields(answer.solution).values():
            if isinstance(v, np.ndarray):
                assert not v.flags.writeable  # as the estimator's own results
        assert est.install(answer)


def test_solver_process_returns_the_error(solver: SolverProcess) -> None:
    _, p, c = _joint("ball", frames=0)
    still_p = np.repeat(p[:1], 300, axis=0)  # no movement, no noise: no joint to find
    still_c = np.repeat(c[:1], 300, axis=0)
    est = OnlineJoint("ball", 1000)
    est.update_many(still_p, still_c)
    request = est.solve_request()
    assert request is not None
    with pytest.raises(NotIdentifiableError) as local:
        solve_window(request)
    solver.submit("hip", request)
    ((key, answer),) = _answer(solver)
    assert key == "hip" and type(answer) is NotIdentifiableError and str(answer) == str(local.value)
    assert solver.alive and solver.idle


def _running(sp: SolverProcess, request: SolveRequest) -> subprocess.Popen[bytes]:
    """Start the worker (it starts with the first request) and wait for its answer."""
    assert sp.submit("first", request)
    assert len(_answer(sp)) == 1
    assert sp._proc is not None and sp._proc.poll() is None
    return sp._proc


def test_the_worker_starts_with_the_first_request() -> None:
    sp = SolverProcess()
    assert not sp.started and sp.alive and sp.idle
    assert sp.collect() == [] and not sp.ready(0.01)
    sp.close()  # never started: nothing to stop
    assert not sp.started and not sp.alive
    est, _, _ = _joint("ball")
    request = est.solve_request()
    assert request is not None
    sp = SolverProcess()
    try:
        proc = _running(sp, request)
    finally:
        sp.close()
    assert proc.poll() is not None and not sp.alive


def test_a_dead_worker_is_noticed(solver: SolverProcess) -> None:
    est, _, _ = _joint("ball")
    request = est.solve_request()
    assert request is not None
    _running(solver, request)
    assert solver._proc is not None
    solver._proc.kill()
    solver._proc.wait()
    solver.submit("hip", request)  # may still succeed: the socket's buffer takes it
    assert _answer(solver) == []
    assert not solver.alive and not solver.idle and "solver process" in solver.problem
    assert not solver.submit("hip", request)


# --------------------------------------------------------------------------- in the node


def _node_estimates(solver_process: bool, kill_worker_at: int | None = None) -> tuple[dict[str, object], list[str]]:
    """An in-process node fed 1500 frames of the fake rigs, its estimate timer ticked every 20 frames.

    Returns the joints' final solutions and the node's diagnostics value "estimates solved in" over time.
    """
    rclpy = pytest.importorskip("rclpy")
    import os
    import tempfile
    from pathlib import Path

    from jointfit_ros.conversions import pose_array_bytes
    from jointfit_ros.fake_mocap import frame_at, make_rigs, marker_names
    from jointfit_ros.node import JointfitNode

    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    with tempfile.TemporaryDirectory() as tmp:
        params = Path(tmp) / "p.yaml"
        params.write_text(
            f"""jointfit:
  ros__parameters:
    joints: [hip, knee]
    marker_names: [{", ".join(marker_names(0))}]
    solver_process: {str(solver_process).lower()}
    hip: {{type: ball, parent_markers: [PELV1, PELV2, PELV3, PELV4], child_markers: [THIGH1, THIGH2, THIGH3, THIGH4], window: 5000}}
    knee: {{type: hinge, parent_markers: [FEMUR1, FEMUR2, FEMUR3, FEMUR4], child_markers: [SHANK1, SHANK2, SHANK3, SHANK4], window: 5000, axis_toward_marker: SHANK1}}
""",
            encoding="utf-8",
        )
        context = rclpy.Context()
        rclpy.init(args=["--ros-args", "--params-file", str(params)], context=context)
        node = JointfitNode(context=context)
        try:
            rigs = make_rigs(3)
            rng = np.random.default_rng(3)
            solved_in: list[str] = []
            for k in range(1500):
                frame = frame_at(rigs, k / 100.0, rng, 0.5, 0.0) / 1000.0
                node._on_markers(pose_array_bytes(10**18 + k * 10**7, "world", frame))
                if k == kill_worker_at:
                    assert node._solver is not None and node._solver._proc is not None
                    node._solver._proc.kill()
                    node._solver._proc.wait()
                if k % 20 == 19:
                    if node._solver is not None:
                        node._solver.ready(30.0)  # the worker's answer (its start takes a second or two)
                    node._on_estimate_timer()
                    solved_in.append("worker" if node._solver is not None else "thread")
            # bring every joint up to the last frame
            for _ in range(8):
                if node._solver is not None:
                    node._solver.ready(30.0)
                node._on_estimate_timer()
            return {name: r.estimator.solution for name, r in node.runners.items()}, solved_in
        finally:
            node.destroy_node()
            rclpy.shutdown(context=context)


@pytest.mark.ros
def test_node_solves_in_the_worker_as_in_process() -> None:
    in_worker, where = _node_estimates(True)
    assert set(where) == {"worker"}
    in_thread, where = _node_estimates(False)
    assert set(where) == {"thread"}
    for name in ("hip", "knee"):
        assert in_worker[name] is not None
        _assert_identical(in_worker[name], in_thread[name])


@pytest.mark.ros
def test_node_falls_back_when_the_worker_dies() -> None:
    solutions, where = _node_estimates(True, kill_worker_at=700)
    assert where[0] == "worker" and where[-1] == "thread"
    assert where.index("thread") <= 700 // 20 + 2  # noticed at the next tick or the one after
    reference, _ = _node_estimates(False)
    for name in ("hip", "knee"):
        _assert_identical(solutions[name], reference[name])


def test_a_hung_worker_is_given_up(solver: SolverProcess, monkeypatch: pytest.MonkeyPatch) -> None:
    import signal

    import jointfit_ros.solver_process as sp_module

    est, _, _ = _joint("ball")
    request = est.solve_request()
    assert request is not None
    worker = _running(solver, request)
    monkeypatch.setattr(sp_module, "SOLVE_TIMEOUT_S", 0.2)
    worker.send_signal(signal.SIGSTOP)  # alive, never answering
    assert solver.submit("hip", request)
    time.sleep(0.3)
    assert solver.collect() == []
    assert not solver.alive and "no answer" in solver.problem
    assert worker.poll() is not None  # killed, not left stopped
