"""Shared helpers for the tests: random rigid transforms and validation indices."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation


def random_rigid(rng: np.random.Generator, scale: float = 1000.0) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """A random rotation matrix and a translation of about ``scale``."""
    return Rotation.random(random_state=rng).as_matrix(), rng.normal(0.0, scale, 3)


def transform(markers: NDArray[np.float64], rot: NDArray[np.float64], trans: NDArray[np.float64]) -> NDArray[np.float64]:
    """Apply ``x -> R x + t`` to every marker (NaN stays NaN)."""
    return np.einsum("ij,npj->npi", rot, markers) + trans


def template_rotation(motion_template: NDArray[np.float64], template: NDArray[np.float64]) -> NDArray[np.float64]:
    """The rotation from a motion's bone frame to an estimator's template frame (their markers' Procrustes)."""
    u, _, vt = np.linalg.svd((motion_template - motion_template.mean(axis=0)).T @ (template - template.mean(axis=0)))
    out: NDArray[np.float64] = vt.T @ np.diag([1.0, 1.0, float(np.sign(np.linalg.det(vt.T @ u.T)))]) @ u.T
    return out


def truth_in_template(
    motion_template: NDArray[np.float64], template: NDArray[np.float64], point: NDArray[np.float64]
) -> NDArray[np.float64]:
    """A point of the motion's bone frame in the estimator's template frame."""
    R = template_rotation(motion_template, template)
    return np.asarray(R @ (point - motion_template.mean(axis=0)) + template.mean(axis=0))


def mahalanobis(err: NDArray[np.float64], cov: NDArray[np.float64]) -> float:
    """``err^T cov^+ err`` divided by the rank of ``cov`` (Stoddart's v^2)."""
    pinv = np.linalg.pinv(cov, rcond=1e-10, hermitian=True)
    rank = int(np.linalg.matrix_rank(cov, tol=1e-10 * np.abs(np.linalg.eigvalsh(cov)).max(), hermitian=True))
    return float(err @ pinv @ err) / rank


def output_index(out: Any, centre: NDArray[np.float64], kind: str) -> float:
    """e/k of one per-frame output (``JointOutput``) against the true joint centre (world, input units).

    Ball: the position's error against its covariance, k = 3. Hinge: the error's part across the output's
    axis direction (a point of the axis may be anywhere along it), k = 2.
    """
    err = out.position - centre
    if kind == "hinge":
        assert out.direction is not None
        err = err - (err @ out.direction) * out.direction
    return float(err @ np.linalg.pinv(out.cov, rcond=1e-12) @ err) / (3.0 if kind == "ball" else 2.0)


def mc_band(values: list[float], low: float = 0.8, high: float = 1.25) -> None:
    """Assert the mean validation index squared lies in the calibration band."""
    mean = float(np.mean(values))
    assert low <= mean <= high, f"mean e/rank = {mean:.3f} outside [{low}, {high}] over {len(values)} trials"


#: Block updates (OnlineJoint.update_many) pose frames with a vectorised eigen-solve, the node's
#: per-frame path with LAPACK: rotations agree to ~1e-13, so sums agree to about this, relative
#: to their largest entry.
SUMS_RTOL = 1e-11


def rel_diff(a: NDArray[np.float64], b: NDArray[np.float64]) -> float:
    """Largest absolute difference over the largest absolute entry of ``b``."""
    return float(np.max(np.abs(a - b)) / max(float(np.max(np.abs(b))), 1e-300))


def assert_same_estimate(a: dict[str, Any], b: dict[str, Any], rtol: float = 1e-9, where: str = "") -> None:
    """Two saved estimates (``to_dict()["estimate"]``): numbers to ``rtol`` of each array's scale, the rest equal."""
    assert a.keys() == b.keys(), where
    for key, vb in b.items():
        va = a[key]
        if isinstance(vb, dict):
            assert_same_estimate(va, vb, rtol, f"{where}{key}.")
        elif isinstance(vb, list):
            arr_a, arr_b = np.array(va, dtype=float), np.array(vb, dtype=float)
            scale = float(np.max(np.abs(arr_b))) if arr_b.size else 0.0
            np.testing.assert_allclose(arr_a, arr_b, rtol=rtol, atol=rtol * scale, err_msg=f"{where}{key}")
        elif isinstance(vb, float):
            assert va == pytest.approx(vb, rel=rtol, abs=1e-300), f"{where}{key}"
        else:
            assert va == vb, f"{where}{key}"


def fake_rig_values(**extra: Any) -> dict[str, Any]:
    """Node parameter values for the fake mocap's hip (ball) and knee (hinge), 20 template frames, plus ``extra``."""
    from jointfit_ros.fake_mocap import marker_names  # (imports ROS messages: only for the tests that use it)

    values: dict[str, Any] = {
        "joints": ["hip", "knee"],
        "marker_names": marker_names(0),
        "input_frame_id": "world",
        "hip.type": "ball",
        "hip.parent_markers": ["PELV1", "PELV2", "PELV3", "PELV4"],
        "hip.child_markers": ["THIGH1", "THIGH2", "THIGH3", "THIGH4"],
        "hip.template_frames": 20,
        "knee.type": "hinge",
        "knee.parent_markers": ["FEMUR1", "FEMUR2", "FEMUR3", "FEMUR4"],
        "knee.child_markers": ["SHANK1", "SHANK2", "SHANK3", "SHANK4"],
        "knee.template_frames": 20,
        # the fake mocap's clusters are rigid (the node's default is skin)
        "hip.attachment": "rigid",
        "knee.attachment": "rigid",
    }
    values.update(extra)
    return values


def rig_frames(n: int, seed: int = 3, rig_seed: int = 3) -> NDArray[np.float64]:
    """``n`` frames (m) of the fake mocap's rigs (:func:`~jointfit_ros.fake_mocap.make_rigs` ``rig_seed``) at 250 Hz, 0.5 mm noise."""
    from jointfit_ros.fake_mocap import frame_at, make_rigs

    rigs = make_rigs(rig_seed)
    rng = np.random.default_rng(seed)
    return np.stack([frame_at(rigs, k * 0.004, rng, 0.5, 0.0) for k in range(n)]) / 1000.0


def rig_router(**extra: Any) -> tuple[Any, list[Any]]:
    """A :class:`~jointfit_ros.inputs.MessageRouter` and its runners for the fake rigs' node values (:func:`fake_rig_values`)."""
    from jointfit_ros.inputs import MessageRouter
    from jointfit_ros.params import node_config
    from jointfit_ros.runner import JointRunner

    cfg = node_config(fake_rig_values(**extra))
    runners = [JointRunner(j, cfg) for j in cfg.joints]
    return MessageRouter(cfg, runners), runners


def diagnostics_status(arrays: list[Any], name: str) -> dict[str, str]:
    """The latest ``jointfit: <name>`` status of received ``DiagnosticArray``s: level, message and key/values."""
    for arr in reversed(arrays):
        for st in arr.status:
            if st.name == f"jointfit: {name}":
                level = st.level[0] if isinstance(st.level, bytes) else st.level
                return {"level": str(level), "message": st.message, **{kv.key: kv.value for kv in st.values}}
    return {}


def stop_processes(procs: list[Any], output_of: Any) -> str:
    """SIGINT each process of ``procs`` still running, wait for it (killed after 10 s); ``output_of``'s output."""
    import signal
    import subprocess

    for proc in procs:
        if proc is not None and proc.poll() is None:
            proc.send_signal(signal.SIGINT)
    output = ""
    for proc in procs:
        if proc is None:
            continue
        try:
            out = proc.communicate(timeout=10)[0]
        except subprocess.TimeoutExpired:
            proc.kill()
            out = proc.communicate()[0]
        if proc is output_of and out:
            output = out.decode(errors="replace")
    return output
