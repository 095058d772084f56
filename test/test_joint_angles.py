"""Joint angles (jointfit_core.joint_angles), ~/joint_states (jointfit_ros.joint_states) and the URDF (jointfit_core.urdf).

Ground truth: the fake lower-body skeleton (jointfit_core.skeleton_truth), run through the
node's per-message path without ROS (MessageRouter -> JointRunner), and pure rotations.
"""

from __future__ import annotations

import re

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from skeleton_runs import T0
from test_skeleton_configs import FILES, RATE

from jointfit_core.errors import InputError
from jointfit_core.joint_angles import (
    angle_rates,
    cardan_xyz,
    hinge_angle,
    hinge_angle_sd,
    rotation_from_cardan_xyz,
)
from jointfit_core.skeleton_truth import make_skeleton, skeleton_frames
from jointfit_core.urdf import urdf_from_calibrations
from jointfit_ros.inputs import MessageRouter
from jointfit_ros.joint_states import JointStates, joint_state_bytes
from jointfit_ros.params import node_config, params_from_file
from jointfit_ros.raw import pose_array_bytes
from jointfit_ros.runner import JointRunner


def test_hinge_angle_of_pure_rotations_and_its_insensitivity_to_swing() -> None:
    rng = np.random.default_rng(3)
    a = rng.normal(size=(200, 3))
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    theta = rng.uniform(-3.1, 3.1, 200)
    Q = Rotation.from_rotvec(a * theta[:, None]).as_matrix()
    np.testing.assert_allclose(hinge_angle(Q, a), theta, atol=1e-12)
    np.testing.assert_allclose(hinge_angle(Q, -a), -theta, atol=1e-12)  # sign by the axis
    # a small swing off the axis changes the angle to second order only
    perp = np.cross(a, rng.normal(size=(200, 3)))
    perp /= np.linalg.norm(perp, axis=1, keepdims=True)
    swung = Rotation.from_rotvec(1e-3 * perp).as_matrix() @ Q
    assert np.abs(hinge_angle(swung, a) - theta).max() < 2e-6
    # sd: the axis term vanishes for a pure rotation; the pose term is a^T C a
    C = np.broadcast_to(np.diag([1e-6, 4e-6, 9e-6]), (200, 3, 3))
    sd = hinge_angle_sd(Q, a, np.broadcast_to(np.eye(3) * 1e-4, (200, 3, 3)), C)
    np.testing.assert_allclose(sd**2, np.einsum("ni,nij,nj->n", a, C, a), rtol=1e-9)


def test_cardan_xyz_is_scipys_intrinsic_xyz_and_inverts() -> None:
    R = Rotation.random(500, random_state=4)
    ang = cardan_xyz(R.as_matrix())
    np.testing.assert_allclose(ang, R.as_euler("XYZ"), atol=1e-9)
    np.testing.assert_allclose(rotation_from_cardan_xyz(ang), R.as_matrix(), atol=1e-12)
    locked = rotation_from_cardan_xyz([0.3, np.pi / 2, 0.2])  # gimbal lock: finite, still reproduces Q
    np.testing.assert_allclose(rotation_from_cardan_xyz(cardan_xyz(locked)), locked, atol=1e-7)
    with pytest.raises(InputError, match=r"shape \(..., 3, 3\)"):
        cardan_xyz(np.eye(4))


def test_angle_rates_cross_the_wrap() -> None:
    t = np.array([0.0, 0.01, 0.02, 0.03])
    ang = np.array([3.10, -3.13, -3.08, np.nan])
    v = angle_rates(ang, t)
    np.testing.assert_allclose(v[1:3], [(2 * np.pi - 6.23) / 0.01, 0.05 / 0.01], atol=1e-9)
    assert np.isnan(v[0]) and np.isnan(v[3])


def _kabsch(y: np.ndarray, x: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd((x - x.mean(0)).T @ (y - y.mean(0)))
    return Vt.T @ np.diag([1.0, 1.0, np.linalg.det(Vt.T @ U.T)]) @ U.T


@pytest.fixture(scope="module")
def skeleton_run() -> dict:
    """8 s of the lower skeleton (0.5 mm noise) in blocks, then 2 s frame by frame with ~/joint_states."""
    sk = make_skeleton("lower", seed=1)
    cfg = node_config(params_from_file(FILES["lower"]))
    t = np.arange(int(10.0 * RATE)) / RATE
    frames = skeleton_frames(sk, t, np.random.default_rng(5), 0.0005, 0.0)
    raws = [pose_array_bytes(T0 + round(tk * 1e9), "world", f) for tk, f in zip(t, frames, strict=True)]
    runners = [JointRunner(j, cfg) for j in cfg.joints]
    router = MessageRouter(cfg, runners)
    n_block = int(8.0 * RATE)
    for start in range(0, n_block, 100):
        router.markers_many(raws[start : start + 100])
    for r in runners:
        assert r.estimate(force=True), r.last_error
        r.freeze(True)
    states = JointStates([(j.name, j.type) for j in cfg.joints])
    per_frame = []
    for k in range(n_block, len(raws)):
        routed = router.markers(raws[k])
        per_frame.append((k, states.frame(T0 + round(t[k] * 1e9), routed), routed))
    return {"sk": sk, "t": t, "runners": runners, "per_frame": per_frame, "raws": raws}


def _node_frame_rotations(sk, runners, t_eval):
    """True Q of every joint in the node's template frames: G_p Q_true G_c^T (G: true template at 0 -> node's)."""
    R_tpl, _ = sk.template_poses_at(t_eval)
    R0 = sk.poses_at([0.0])[0][0]
    index = {s.name: i for i, s in enumerate(sk.segments)}
    out = {}
    for r in runners:
        s = sk.joint_segment(r.cfg.name)
        p, c = index[s.parent], index[s.name]
        G = []
        for seg, tpl in ((p, r.estimator.templates[0]), (c, r.estimator.templates[1])):
            m = sk.segments[seg].markers
            G.append(_kabsch(tpl, (m - m.mean(0)) @ R0[seg].T))
        Q_true = np.swapaxes(R_tpl[:, p], 1, 2) @ R_tpl[:, c]
        out[r.cfg.name] = (G[0] @ Q_true @ G[1].T, G[0], s)
    return out


def test_joint_states_match_the_truth_within_their_sd(skeleton_run: dict) -> None:
    sk, t, runners, per_frame = skeleton_run["sk"], skeleton_run["t"], skeleton_run["runners"], skeleton_run["per_frame"]
    ks = np.array([k for k, _, _ in per_frame])
    truth = _node_frame_rotations(sk, runners, t[ks])
    e_angle, e_vel, ball_err, ball_scale = [], [], [], []
    for r in runners:
        name = r.cfg.name
        Q_true, Gp, s = truth[name]
        cols = [name] if r.cfg.type == "hinge" else [f"{name}_{a}" for a in "xyz"]
        got = np.array([[fa.position[fa.names.index(c)] for c in cols] for _, fa, _ in per_frame])
        vel = np.array([[fa.velocity[fa.names.index(c)] for c in cols] for _, fa, _ in per_frame])
        if r.cfg.type == "hinge":
            sd = np.array([fa.sd[fa.names.index(name)] for _, fa, _ in per_frame])
            a_true = Gp @ sk.joints_local(0.0)[name].direction
            a_est = r.estimator.solution.direction_parent
            sign = np.sign(a_est @ a_true)
            true_angle = sign * hinge_angle(Q_true, a_true)
            # against the skeleton's own angle (deg, component 0 of its motion), zeroed at t = 0
            wave = np.sin(2 * np.pi * s.freq[0] * t[ks] / sk.cycle_s + s.phase[0])
            wave0 = np.sin(s.phase[0])
            spec = sign * np.deg2rad(s.amp_deg[0] * (wave - wave0))
            err = got[:, 0] - true_angle
            # The node's zero is its templates' pose: the posture at the first template frame up to that
            # frame's pose-fit error (a template is aligned to its first frame), a constant of ~1 frame's sd.
            offset = true_angle - spec
            assert np.ptp(offset) < 1e-3 and abs(offset.mean()) < 4.0 * np.median(sd), (name, offset.mean())
            e_angle.append(np.mean((err / sd) ** 2))
            # velocity: backward difference; its error sd from the two frames' angle sds
            true_vel = sign * np.deg2rad(s.amp_deg[0]) * 2 * np.pi * s.freq[0] / sk.cycle_s * np.cos(
                2 * np.pi * s.freq[0] * (t[ks] - 0.5 / RATE) / sk.cycle_s + s.phase[0]
            )
            ev = (vel[1:, 0] - true_vel[1:]) / (np.sqrt(sd[1:] ** 2 + sd[:-1] ** 2) * RATE)
            e_vel.append(np.mean(ev**2))
            assert np.isnan(vel[0, 0])  # the first frame after the blocks has no previous angle
        else:
            true_ang = cardan_xyz(Q_true)
            ball_err.append(np.sqrt(np.mean((got - true_ang) ** 2)))
            CQ = np.stack([next(x.output for x in routed if x.runner is r).rotation_cov for _, _, routed in per_frame])
            ball_scale.append(np.sqrt(np.mean(np.trace(CQ, axis1=1, axis2=2) / 3)))
    print("hinge e:", np.round(e_angle, 2), "velocity e:", np.round(e_vel, 2))
    print("ball rms err / pose sd:", np.round(np.array(ball_err) / np.array(ball_scale), 2))
    # calibrated: mean (err/sd)^2 near 1 (200 frames each; template offsets add a little)
    assert all(0.3 < e < 2.5 for e in e_angle), e_angle
    assert all(0.3 < e < 2.5 for e in e_vel), e_vel
    # ball angles: within the pose noise (Cardan rates differ from the rotation-vector sd by O(1))
    assert all(err < 3.0 * scale for err, scale in zip(ball_err, ball_scale, strict=True)), (ball_err, ball_scale)


def test_joint_state_bytes_deserialise_with_rclpy(skeleton_run: dict) -> None:
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import JointState

    _, fa, _ = skeleton_run["per_frame"][5]
    msg = deserialize_message(joint_state_bytes(T0 + 123, "world", fa), JointState)
    assert list(msg.name) == fa.names and msg.header.frame_id == "world"
    assert msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec == T0 + 123
    np.testing.assert_array_equal(msg.position, fa.position)
    np.testing.assert_array_equal(msg.velocity, fa.velocity)
    assert len(msg.effort) == 0
    assert fa.names == ["r_hip_x", "r_hip_y", "r_hip_z", "r_knee", "r_ankle", "l_hip_x", "l_hip_y", "l_hip_z",
                        "l_knee", "l_ankle"]


def _calibrations(runners) -> list[dict]:
    out = []
    for r in runners:
        data = r.estimator.to_dict()
        data.update(r.identity())
        out.append(data)
    return out


def _link(markers: tuple[str, ...]) -> str:
    return re.sub(r"\d+$", "", markers[0])


def test_urdf_forward_kinematics_reproduce_the_segment_poses(skeleton_run: dict, tmp_path) -> None:
    yourdfpy = pytest.importorskip("yourdfpy")
    sk, t, runners, per_frame = skeleton_run["sk"], skeleton_run["t"], skeleton_run["runners"], skeleton_run["per_frame"]
    path = tmp_path / "subject.urdf"
    path.write_text(urdf_from_calibrations(_calibrations(runners)))
    robot = yourdfpy.URDF.load(str(path), build_scene_graph=True, load_meshes=False)
    assert robot.validate()
    assert set(robot.actuated_joint_names) == set(per_frame[0][1].names)
    assert set(robot.link_map) >= {"PELV", "RTHI", "RSHK", "RFOO", "LTHI", "LSHK", "LFOO"}
    picked = per_frame[::10]
    ks = np.array([k for k, _, _ in picked])
    truth = _node_frame_rotations(sk, runners, t[ks])
    R_tpl, origin = sk.template_poses_at(t[ks])
    index = {s.name: i for i, s in enumerate(sk.segments)}
    sigma = 0.0005
    for r in runners:
        name = r.cfg.name
        Q_true, Gp, s = truth[name]
        p, c = index[s.parent], index[s.name]
        t_true = np.einsum("nji,nj->ni", R_tpl[:, p], origin[:, c] - origin[:, p]) @ Gp.T  # node's parent frame
        sol = r.estimator.solution
        if r.cfg.type == "hinge":
            a_true = Gp @ sk.joints_local(0.0)[name].direction
            sign = np.sign(sol.direction_parent @ a_true)
            true_angles = (sign * hinge_angle(Q_true, a_true))[:, None]
            lever = np.linalg.norm(sol.point_child)
        else:
            true_angles = cardan_xyz(Q_true)
            lever = np.linalg.norm(sol.centre_child)
        cols = [name] if r.cfg.type == "hinge" else [f"{name}_{a}" for a in "xyz"]
        published = np.array([[fa.position[fa.names.index(col)] for col in cols] for _, fa, _ in picked])
        for label, angle_rows in (("true", true_angles), ("published", published)):
            for k, (_, _fa, routed) in enumerate(picked):
                out = next(x.output for x in routed if x.runner is r)
                robot.update_cfg(dict(zip(cols, angle_rows[k], strict=True)))
                T = robot.get_transform(_link(r.cfg.child_markers), _link(r.cfg.parent_markers))
                delta = Rotation.from_matrix(T[:3, :3] @ Q_true[k].T).as_rotvec()  # left error, parent frame
                pos_err = np.linalg.norm(T[:3, 3] - t_true[k])
                # within the pose noise: this frame's relative rotation covariance (chi^2, 3 dof, p ~ 1e-5), and
                # at the child's origin the lever times its largest sd plus the template origins' noise
                e_rot = float(delta @ np.linalg.solve(out.rotation_cov, delta))
                rot_sd_max = np.sqrt(np.linalg.eigvalsh(out.rotation_cov)[-1])
                assert e_rot < 25.0, (name, label, k, e_rot)
                assert pos_err < 4.0 * (lever * rot_sd_max + sigma), (name, label, k, pos_err)
                if label == "true" and r.cfg.type == "ball":
                    assert np.linalg.norm(delta) < 1e-9  # the XYZ chain is the Cardan decomposition exactly


def test_urdf_refuses_what_is_not_one_tree(skeleton_run: dict) -> None:
    cals = _calibrations(skeleton_run["runners"])
    with pytest.raises(InputError, match="child of both"):
        urdf_from_calibrations([*cals, dict(cals[1], joint="r_knee2")])
    with pytest.raises(InputError, match="names repeat"):
        urdf_from_calibrations([*cals, cals[1]])
    with pytest.raises(InputError, match="separate trees"):
        urdf_from_calibrations([cals[1], cals[2], cals[5]])  # r_knee, r_ankle, l_ankle
    broken = dict(cals[0])
    del broken["parent_markers"]
    with pytest.raises(InputError, match="joint's record"):
        urdf_from_calibrations([broken])


def test_jointfit_urdf_command(skeleton_run: dict, tmp_path) -> None:
    import subprocess
    import sys

    from jointfit_core.calibration import save_calibration

    paths = [str(save_calibration(tmp_path / f"{k}.yaml", c)) for k, c in enumerate(_calibrations(skeleton_run["runners"]))]
    done = subprocess.run([sys.executable, "-m", "jointfit_ros.cli", "urdf", *paths], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith("<?xml") and done.stdout.count("<joint ") == 6 * 2 + 2 * 2  # 4 hinges x2, 2 balls x4
    bad = subprocess.run([sys.executable, "-m", "jointfit_ros.cli", "urdf", paths[1], paths[5]], capture_output=True, text=True)
    assert bad.returncode == 1 and "separate trees" in bad.stderr and "Traceback" not in bad.stderr
