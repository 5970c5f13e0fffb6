"""UR5e kinematics: the DH forward map against hand-checked poses, the analytic inverse
against the forward map, and unreachable poses refused with the reason."""
import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from cell.core import geometry
from cell.devices import ur5e

joint = st.floats(-np.pi, np.pi, allow_nan=False)
elbow = st.floats(-0.95 * np.pi, 0.95 * np.pi).filter(lambda q: abs(np.sin(q)) > 0.02)
joints = st.tuples(joint, joint, elbow, joint, joint, joint).map(np.array)


def regular(q):
    """Away from the wrist singularity (q5 near 0 or pi) and the shoulder singularity (the wrist
    centre on the cylinder of radius d4 about the base axis, where q1 is not unique)."""
    T = ur5e.forward(q)
    wrist = T[:3, 3] - ur5e.D[5] * T[:3, 2]
    return abs(np.sin(q[4])) > 0.02 and np.hypot(wrist[0], wrist[1]) > ur5e.D[3] + 1e-3


def test_zero_joints_stretch_the_arm_along_minus_x_tool_along_minus_y():
    # by hand: x = a2 + a3, y = -(d4 + d6), z = d1 - d5; the flange frame is Rx(+90 deg)
    T = ur5e.forward(np.zeros(6))
    assert T[:3, 3] == pytest.approx([-0.425 - 0.3922, -0.1333 - 0.0996, 0.1625 - 0.0997], abs=1e-12)
    assert T[:3, :3] == pytest.approx(np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]]), abs=1e-12)


def test_base_joint_turns_the_zero_pose_about_z():
    T0, T90 = ur5e.forward(np.zeros(6)), ur5e.forward([np.pi / 2, 0, 0, 0, 0, 0])
    Rz = geometry.transform(np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1]]))
    assert T90 == pytest.approx(Rz @ T0, abs=1e-12)


@settings(max_examples=300, deadline=None)
@given(joints)
def test_every_inverse_solution_reaches_the_pose_and_one_is_the_generating_joints(q):
    assume(regular(q))
    T = ur5e.forward(q)
    solutions = ur5e.inverse_all(T)
    for s in solutions:
        assert ur5e.forward(s) == pytest.approx(T, abs=1e-9)
    wrapped = (q + np.pi) % (2 * np.pi) - np.pi
    assert min(np.max(np.abs(np.angle(np.exp(1j * (s - wrapped))))) for s in solutions) < 1e-6


def test_a_pose_in_front_of_the_robot_has_all_eight_solutions():
    T = ur5e.forward(np.radians([-90.0, -90.0, 90.0, -90.0, -90.0, 0.0]))
    solutions = ur5e.inverse_all(T)
    assert len(solutions) == 8
    assert len({tuple(np.round(s, 6)) for s in solutions}) == 8


@settings(max_examples=300, deadline=None)
@given(joints, st.floats(-0.2, 0.2), st.integers(0, 5))
def test_inverse_picks_the_solution_nearest_the_current_joints(q, step, j):
    assume(regular(q))
    q_near = q.copy()
    q_near[j] += step                                  # a small move from where the arm is
    T = ur5e.forward(q)
    solution = ur5e.inverse(T, q_near)
    assert ur5e.forward(solution) == pytest.approx(T, abs=1e-9)
    # near a branch boundary another solution may be nearer still, never farther
    assert np.max(np.abs(solution - q_near)) <= np.max(np.abs(q - q_near)) + 1e-9


@settings(max_examples=60, deadline=None)
@given(joints, joints)
def test_inverse_takes_the_smallest_largest_step_of_every_solution_and_turn(q, q_near):
    """Brute force: every closed-form solution with each joint turned by -2 pi, 0 or +2 pi (3^6
    turns) within the limits; none has a smaller largest step from q_near than inverse's answer."""
    import itertools
    assume(regular(q))
    T = ur5e.forward(q)
    solution = ur5e.inverse(T, q_near)
    turns = 2 * np.pi * np.array(list(itertools.product((-1.0, 0.0, 1.0), repeat=6)))
    every = (ur5e.inverse_all(T, q6_free=q_near[5])[:, None, :] + turns[None]).reshape(-1, 6)
    every = every[np.all(np.abs(every) <= ur5e.JOINT_LIMITS, axis=1)]
    assert np.max(np.abs(solution - q_near)) == np.min(np.max(np.abs(every - q_near), axis=1))
    assert np.all(np.abs(solution) <= ur5e.JOINT_LIMITS)
    assert ur5e.forward(solution) == pytest.approx(T, abs=1e-9)


def test_a_small_step_from_home_stays_on_the_same_branch():
    home = np.radians([-90.0, -90.0, 90.0, -90.0, -90.0, 0.0])
    q = home + np.radians([3.0, -2.0, 4.0, 1.0, -2.0, 5.0])
    assert ur5e.inverse(ur5e.forward(q), home) == pytest.approx(q, abs=1e-9)


def test_inverse_keeps_joints_within_limits_and_unwraps_toward_the_current_joints():
    q = np.array([-3.0, -1.0, 1.2, -1.5, -1.6, 3.1])
    near = q + np.array([2 * np.pi, 0, 0, 0, 0, -2 * np.pi]) + 0.01     # the same pose, unwrapped
    solution = ur5e.inverse(ur5e.forward(q), near)
    assert solution == pytest.approx(q + [2 * np.pi, 0, 0, 0, 0, -2 * np.pi], abs=1e-6)
    assert np.all(np.abs(solution) <= ur5e.JOINT_LIMITS)


def test_wrist_singular_pose_keeps_the_current_last_joint():
    q = np.array([0.3, -1.2, 1.0, -1.4, 0.0, 0.7])      # q5 = 0: q4 and q6 turn the same axis
    solution = ur5e.inverse(ur5e.forward(q), q)
    assert ur5e.forward(solution) == pytest.approx(ur5e.forward(q), abs=1e-9)


def test_pose_beyond_reach_says_how_far():
    T = geometry.transform(translation=(1.2, 0.0, 0.3))
    with pytest.raises(ur5e.Unreachable, match="wrist .* mm from the shoulder, the arm spans"):
        ur5e.inverse(T, np.zeros(6))


def test_pose_on_the_base_axis_says_shoulder_cylinder():
    T = geometry.transform(translation=(0.0, 0.0, 0.5))
    with pytest.raises(ur5e.Unreachable, match="shoulder cylinder"):
        ur5e.inverse_all(T)


def test_dh_of_an_array_is_each_angles_own_matrix_bit_for_bit():
    theta = np.random.default_rng(3).uniform(-4, 4, (7, 3))
    for i in range(6):
        many = ur5e.dh(i, theta)
        assert many.shape == (7, 3, 4, 4)
        assert all(np.array_equal(many[a, b], ur5e.dh(i, float(theta[a, b]))) for a in range(7) for b in range(3))


def test_many_poses_solved_at_once_get_each_ones_own_joints_and_refusals():
    """nearest's poses together: each the very joints inverse gives it alone (the planner's plans
    must not depend on how many poses were asked with it), the forward map reproducing the pose,
    and exactly the poses inverse refuses (beyond reach, in the shoulder cylinder) unreached."""
    rng = np.random.default_rng(7)
    poses = []
    for k in range(400):
        q = rng.uniform(-np.pi, np.pi, 6)
        q[4] = 0.0 if k % 9 == 0 else q[4]                 # wrist singular: q6 takes q_near's
        T = ur5e.forward(q)
        T[:3, 3] *= 1.8 if k % 5 == 0 else 1.0             # some beyond reach
        T[:2, 3] = (0.05, 0.0) if k % 31 == 0 else T[:2, 3]  # some on the base axis
        poses.append(T)
    poses = np.array(poses)
    q_near = rng.uniform(-1, 1, 6)
    q, reached = ur5e.nearest(poses, q_near)
    assert 0 < reached.sum() < len(poses)
    for T, qk, ok in zip(poses, q, reached):
        if not ok:
            with pytest.raises(ur5e.Unreachable):
                ur5e.inverse(T, q_near)
            assert np.all(np.isnan(qk))
            continue
        assert np.array_equal(ur5e.inverse(T, q_near), qk)
        assert ur5e.forward(qk) == pytest.approx(T, abs=1e-6)      # 1e-9 away from the singularities

