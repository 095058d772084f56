"""Solving a window elsewhere: OnlineJoint.solve_request / solve_window / install, and the node's solver process.

The node sends every joint's due window to a worker process
(jointfit_ros.solver_process) in one request, so that solves do not delay the
frames. Each answer must equal the in-process estimate bit for bit, stale
answers (a reset, freeze, new sign convention, or a newer estimate installed
meanwhile) must be dropped joint by joint, errors must arrive as the
estimator's own exceptions and as that joint's alone, and a worker that dies
or hangs must be noticed.
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
from jointfit_ros.solver_process import SolverProcess, solve_batch

FloatArray = NDArray[np.float64]


def _joint(
    kind: str, frames: int = 1500, seed: int = 5, attachment: str = "rigid"
) -> tuple[OnlineJoint, FloatArray, FloatArray]:
    """An estimator fed ``frames`` frames of a synthetic rig (0.5 mm noise), and the next 200 frames."""
    rng = np.random.default_rng(seed)
    m = two_segment_motion(rng, kind=kind)
    t = np.arange(frames + 200) / 100.0
    p, c = m.markers_at(t)
    p = p + rng.normal(0.0, 0.5, p.shape)
    c = c + rng.normal(0.0, 0.5, c.shape)
    est = OnlineJoint(kind, 1000, attachment=attachment)
    est.update_many(p[:frames], c[:frames], t[:frames] if attachment == "skin" else None)
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


def _requests(kinds: str, seed: int = 7) -> list[tuple[str, OnlineJoint, SolveRequest]]:
    """``(key, estimator, request)`` of one joint per letter of ``kinds``, each its own rig.

    b / h: a rigid ball / hinge; B / H: with skin attachment (the soft-tissue part, a second solution).
    """
    out = []
    for k, letter in enumerate(kinds):
        kind = {"b": "ball", "h": "hinge"}[letter.lower()]
        attachment = "skin" if letter.isupper() else "rigid"
        est, _, _ = _joint(kind, frames=1000 + 100 * k, seed=seed + k, attachment=attachment)
        request = est.solve_request()
        assert request is not None
        out.append((f"{kind}{k}", est, request))
    return out


def test_solver_process_equals_in_process(solver: SolverProcess) -> None:
    joints = _requests("bhHBbh")
    batch = [(key, request) for key, _, request in joints]
    assert solver.idle and solver.submit(batch)
    assert not solver.idle and not solver.submit(batch)  # one batch at a time
    answers = _answer(solver)
    assert [key for key, _ in answers] == [key for key, _ in batch]  # all of them, in one answer, in order
    assert solver.idle and solver.collect() == []
    for (key, answer), (_, est, request) in zip(answers, joints, strict=True):
        assert isinstance(answer, SolveResult), key
        local = solve_window(request)
        _assert_identical(answer.solution, local.solution)
        assert answer.noise_std == local.noise_std
        assert (answer.statistical is None) == (local.statistical is None) == (request.attachment == ("rigid", "rigid"))
        if answer.statistical is not None:  # skin: the statistical part too
            _assert_identical(answer.statistical, local.statistical)
            assert answer.artefact_scale == local.artefact_scale
        for part in (answer.solution, answer.statistical or answer.solution):
            for v in _fields(part).values():
                if isinstance(v, np.ndarray):
                    assert not v.flags.writeable  # as the estimator's own results
        assert est.install(answer)
    # the next batch goes to the same worker
    proc = solver._proc
    est, _, _ = _joint("ball", seed=11)
    request = est.solve_request()
    assert request is not None and solver.submit([("again", request)])
    ((key, answer),) = _answer(solver)
    assert key == "again" and isinstance(answer, SolveResult) and solver._proc is proc
    _assert_identical(answer.solution, solve_window(request).solution)


def _still_request() -> SolveRequest:
    """A window without movement or noise: no joint to find (the solve raises NotIdentifiableError)."""
    _, p, c = _joint("ball", frames=0)
    est = OnlineJoint("ball", 1000)
    est.update_many(np.repeat(p[:1], 300, axis=0), np.repeat(c[:1], 300, axis=0))
    request = est.solve_request()
    assert request is not None
    return request


def test_solver_process_returns_each_joints_error(solver: SolverProcess) -> None:
    """A solve that raises is that joint's answer; the joints before and after it in the batch are solved."""
    still = _still_request()
    with pytest.raises(NotIdentifiableError) as local:
        solve_window(still)
    (_, _, ball), (_, _, hinge) = _requests("bh", seed=3)
    broken = dataclasses.replace(ball, sums=ball.sums[:10])  # a bug's stand-in: not a JointfitError
    with pytest.raises(Exception) as bug:
        solve_window(broken)
    assert not isinstance(bug.value, JointfitError)
    batch = [("ball", ball), ("hip", still), ("bug", broken), ("hinge", hinge)]
    assert solver.submit(batch)
    answers = dict(_answer(solver))
    assert list(answers) == ["ball", "hip", "bug", "hinge"]
    assert type(answers["hip"]) is NotIdentifiableError and str(answers["hip"]) == str(local.value)
    assert type(answers["bug"]) is JointfitError
    assert str(answers["bug"]) == f"solver process: {type(bug.value).__name__}: {bug.value}"
    for key, request in (("ball", ball), ("hinge", hinge)):
        answer = answers[key]
        assert isinstance(answer, SolveResult), key
        _assert_identical(answer.solution, solve_window(request).solution)
    assert solver.alive and solver.idle


def test_solve_batch_is_what_the_worker_answers() -> None:
    """The worker's function in this process: the same answers, errors in their joint's place."""
    (_, _, ball), (_, _, hinge) = _requests("bh", seed=3)
    answers = solve_batch([("hinge", hinge), ("hip", _still_request()), ("ball", ball)])
    assert [key for key, _ in answers] == ["hinge", "hip", "ball"]
    assert isinstance(answers[1][1], NotIdentifiableError)
    for (_, answer), request in ((answers[0], hinge), (answers[2], ball)):
        assert isinstance(answer, SolveResult)
        _assert_identical(answer.solution, solve_window(request).solution)
    assert solve_batch([]) == []


def test_a_batch_takes_one_request_per_key() -> None:
    sp = SolverProcess()
    (_, _, request), = _requests("b")
    for batch in ([], [("hip", request), ("hip", request)]):
        with pytest.raises(ValueError, match="one request per key"):
            sp.submit(batch)
    assert not sp.started and sp.idle  # refused before anything was started or sent
    sp.close()


def test_stale_answers_of_a_batch_are_dropped_per_joint(solver: SolverProcess) -> None:
    """Runners of one batch: each answer is installed or dropped by its own joint's state at arrival."""
    from jointfit_ros.params import node_config
    from jointfit_ros.runner import JointRunner

    names = [f"{s}{i}" for s in ("P", "C", "Q", "D", "R", "E") for i in range(4)]
    values = {
        "joints": ["hip", "knee", "ankle"],
        "units": "mm",
        "marker_names": names,
        "hip.parent_markers": names[0:4], "hip.child_markers": names[4:8],
        "knee.type": "hinge", "knee.parent_markers": names[8:12], "knee.child_markers": names[12:16],
        "ankle.parent_markers": names[16:20], "ankle.child_markers": names[20:24],
    }  # fmt: skip
    for joint in values["joints"]:
        values[f"{joint}.window"] = 800
        values[f"{joint}.template_frames"] = 20
    cfg = node_config(values)
    rng = np.random.default_rng(2)
    parts = []
    for kind in ("ball", "hinge", "ball"):
        yp, yc = two_segment_motion(rng, kind=kind).markers_at(np.arange(700) / 100.0)
        parts += [yp, yc]
    frames = np.concatenate(parts, axis=1) + rng.normal(0.0, 0.5, (700, 24, 3))
    frames[:, 16:24] = frames[0, 16:24]  # the ankle never moves (and is noiseless): its solve raises
    runners = {j.name: JointRunner(j, cfg) for j in cfg.joints}
    for k in range(600):
        for runner in runners.values():
            runner.markers_frame(10**9 + k * 10**7, frames[k])
    requests = {name: runner.solve_request(force=True) for name, runner in runners.items()}
    assert all(r is not None for r in requests.values())
    assert solver.submit([(name, r) for name, r in requests.items() if r is not None])
    # meanwhile: the hip is reset and fed again, the knee takes new frames, the ankle is left alone
    runners["hip"].reset()
    for k in range(600, 700):
        for name in ("hip", "knee"):
            runners[name].markers_frame(10**9 + k * 10**7, frames[k])
    answers = dict(_answer(solver))
    assert isinstance(answers["hip"], SolveResult) and isinstance(answers["knee"], SolveResult)
    assert isinstance(answers["ankle"], NotIdentifiableError)
    installed = {name: runners[name].install(answers[name], requests[name]) for name in runners}
    assert installed == {"hip": False, "knee": True, "ankle": False}
    assert runners["hip"].estimator.solution is None  # the reset joint kept nothing of the old window
    assert runners["hip"].counters["estimate_failures"] == 0
    assert runners["knee"].estimator.solution is answers["knee"].solution  # older than its frames, still the newest
    assert runners["ankle"].counters["estimate_failures"] == 1 and "no estimate" in runners["ankle"].last_error
    # a second round: the ankle is reset meanwhile, so its error is about a window that is gone: dropped uncounted
    requests = {name: runner.solve_request(force=True) for name, runner in runners.items()}
    assert requests["hip"] is not None and requests["ankle"] is not None
    assert solver.submit([(name, r) for name, r in requests.items() if r is not None])
    runners["ankle"].reset()
    answers = dict(_answer(solver))
    assert runners["hip"].install(answers["hip"], requests["hip"])
    assert not runners["ankle"].install(answers["ankle"], requests["ankle"])
    assert runners["ankle"].counters["estimate_failures"] == 0
    reference = JointRunner(cfg.joints[0], cfg)
    for k in range(600, 700):
        reference.markers_frame(10**9 + k * 10**7, frames[k])
    assert reference.estimate(force=True)
    _assert_identical(runners["hip"].estimator.solution, reference.estimator.solution)


def _running(sp: SolverProcess, request: SolveRequest) -> subprocess.Popen[bytes]:
    """Start the worker (it starts with the first request) and wait for its answer."""
    assert sp.submit([("first", request)])
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


@pytest.mark.parametrize("when", ["idle", "next batch", "solving"])
def test_a_dead_worker_is_noticed(solver: SolverProcess, when: str) -> None:
    """Killed while idle (seen by collect alone), before the next batch, or while it solves one."""
    joints = _requests("bh")
    batch = [(key, request) for key, _, request in joints]
    _running(solver, batch[0][1])
    assert solver._proc is not None
    if when == "solving":
        assert solver.submit(batch)
    solver._proc.kill()
    solver._proc.wait()
    if when == "next batch":
        solver.submit(batch)  # may still succeed: the socket's buffer takes it
    assert _answer(solver) == []
    assert not solver.alive and not solver.idle and "solver process" in solver.problem
    if when != "next batch":
        assert "solver process ended" in solver.problem
    assert not solver.submit(batch)


# --------------------------------------------------------------------------- in the node


@dataclasses.dataclass
class _NodeRun:
    """What :func:`_node_estimates` saw: final solutions, and per estimate tick where it solved and its period."""

    solutions: dict[str, object]
    solved_in: list[str]  # "worker" or "thread", per tick
    periods_ns: list[int]  # the estimate timer's period after each tick
    batches: list[list[str]]  # the joints of each batch sent to the worker


def _node_estimates(solver_process: bool, kill_worker_at: int | None = None) -> _NodeRun:
    """An in-process node fed 1500 frames of the fake rigs, its estimate timer ticked every 20 frames."""
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
    joints: [hip, knee, pelvis]
    marker_names: [{", ".join(marker_names(0))}]
    solver_process: {str(solver_process).lower()}
    hip: {{type: ball, parent_markers: [PELV1, PELV2, PELV3, PELV4], child_markers: [THIGH1, THIGH2, THIGH3, THIGH4], window: 5000}}
    knee: {{type: hinge, parent_markers: [FEMUR1, FEMUR2, FEMUR3, FEMUR4], child_markers: [SHANK1, SHANK2, SHANK3, SHANK4], window: 5000, axis_toward_marker: SHANK1}}
    pelvis: {{type: ball, parent_markers: [THIGH1, THIGH2, THIGH3, THIGH4], child_markers: [PELV1, PELV2, PELV3, PELV4], window: 5000}}
""",
            encoding="utf-8",
        )
        context = rclpy.Context()
        rclpy.init(args=["--ros-args", "--params-file", str(params)], context=context)
        node = JointfitNode(context=context)
        try:
            rigs = make_rigs(3)
            rng = np.random.default_rng(3)
            run = _NodeRun({}, [], [], [])
            if node._solver is not None:
                submit = node._solver.submit

                def recording(batch: list[tuple[str, SolveRequest]]) -> bool:
                    sent = submit(batch)
                    if sent:
                        run.batches.append([key for key, _ in batch])
                    return sent

                node._solver.submit = recording  # type: ignore[method-assign]
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
                    run.solved_in.append("worker" if node._solver is not None else "thread")
                    run.periods_ns.append(node._jf_timers["estimate"].timer_period_ns)
            # bring every joint up to the last frame
            for _ in range(8):
                if node._solver is not None:
                    node._solver.ready(30.0)
                node._on_estimate_timer()
            run.solutions = {name: r.estimator.solution for name, r in node.runners.items()}
            return run
        finally:
            node.destroy_node()
            rclpy.shutdown(context=context)


@pytest.mark.ros
def test_node_solves_in_the_worker_as_in_process() -> None:
    in_worker = _node_estimates(True)
    assert set(in_worker.solved_in) == {"worker"}
    # every joint in every batch, one batch every other tick (a tick sends, the next installs)
    assert in_worker.batches and all(keys == ["hip", "knee", "pelvis"] for keys in in_worker.batches)
    assert len(in_worker.batches) >= (1500 // 20) // 2
    assert set(in_worker.periods_ns) == {round(0.1 / 2 * 1e9)}  # estimate_period / 2, whatever the joint count
    in_thread = _node_estimates(False)
    assert set(in_thread.solved_in) == {"thread"}
    assert set(in_thread.periods_ns) == {round(0.1 / 3 * 1e9)}  # estimate_period / joints: one joint per tick
    for name in ("hip", "knee", "pelvis"):
        assert in_worker.solutions[name] is not None
        _assert_identical(in_worker.solutions[name], in_thread.solutions[name])


@pytest.mark.ros
def test_node_falls_back_when_the_worker_dies() -> None:
    run = _node_estimates(True, kill_worker_at=700)
    where = run.solved_in
    assert where[0] == "worker" and where[-1] == "thread"
    assert where.index("thread") <= 700 // 20 + 2  # noticed at the next tick or the one after
    switched = where.index("thread")
    assert set(run.periods_ns[:switched]) == {round(0.1 / 2 * 1e9)}
    assert set(run.periods_ns[switched:]) == {round(0.1 / 3 * 1e9)}  # re-armed: one joint per tick, in turn
    reference = _node_estimates(False)
    for name in ("hip", "knee", "pelvis"):
        _assert_identical(run.solutions[name], reference.solutions[name])


def test_a_hung_worker_is_given_up(solver: SolverProcess, monkeypatch: pytest.MonkeyPatch) -> None:
    import signal

    import jointfit_ros.solver_process as sp_module

    est, _, _ = _joint("ball")
    request = est.solve_request()
    assert request is not None
    worker = _running(solver, request)
    monkeypatch.setattr(sp_module, "SOLVE_TIMEOUT_S", 0.2)
    worker.send_signal(signal.SIGSTOP)  # alive, never answering
    assert solver.submit([("hip", request), ("knee", _requests("h")[0][2])])
    assert solver.collect() == []  # not yet timed out: waiting
    assert solver.alive and not solver.idle
    time.sleep(0.3)
    assert solver.collect() == []
    assert not solver.alive and "no answer" in solver.problem
    assert worker.poll() is not None  # killed, not left stopped
