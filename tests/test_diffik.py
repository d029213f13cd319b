"""OsqpDifferentialIK: the QP it solves, convergence, limits, singularities and failure handling."""

import dataclasses
from types import SimpleNamespace

import numpy as np
import osqp
import pinocchio as pin
import pytest
from scipy.optimize import lsq_linear

from trivla_drake.robot.osqp_diffik import (
    PANDA_HOME,
    DiffIKParams,
    DiffIKStatus,
    OsqpDifferentialIK,
    pose_error,
)
from trivla_drake.robot.panda_kinematics import PandaKinematics

HOME = np.array(PANDA_HOME)
# Tolerance on joint limits: the solver clips into its box, so only rounding is left.
LIMIT_TOL = 1e-9


@pytest.fixture(scope="module")
def kinematics():
    return PandaKinematics()


def _offset_pose(pose, translation=(0.0, 0.0, 0.0), rpy=(0.0, 0.0, 0.0)):
    target = pose.copy()
    target[:3, 3] += translation
    target[:3, :3] = pin.rpy.rpyToMatrix(*rpy) @ pose[:3, :3]
    return target


def _random_rotation(rng):
    return pin.Quaternion(rng.normal(size=4)).normalized().matrix()


def _run(ik, q, target, ticks):
    """Iterate q <- q_next; return the final q and the per-tick results."""
    results = []
    for _ in range(ticks):
        result = ik.solve(q, target)
        results.append(result)
        q = result.q_next
    return q, results


def _assert_safe(kinematics, params, q, result):
    """Finite output, velocity within the scaled limits, q_next within the URDF limits."""
    assert np.isfinite(result.v).all() and np.isfinite(result.q_next).all()
    assert np.all(np.abs(result.v) <= params.velocity_scale * kinematics.v_max + LIMIT_TOL)
    assert np.all(result.q_next >= kinematics.q_lower - LIMIT_TOL)
    assert np.all(result.q_next <= kinematics.q_upper + LIMIT_TOL)
    np.testing.assert_allclose(result.q_next, q + params.dt * result.v, atol=1e-15)


def _reference_velocity(kinematics, params, q, target):
    """The documented QP, rebuilt with numpy and solved by scipy's bounded least squares."""
    pose, jacobian = kinematics.forward(q)
    twist = params.gain / params.dt * pose_error(pose, target)
    for part, cap in ((slice(0, 3), params.max_linear_speed), (slice(3, 6), params.max_angular_speed)):
        norm = np.linalg.norm(twist[part])
        if norm > cap:
            twist[part] *= cap / norm
    row_scale = np.sqrt([1.0, 1.0, 1.0] + [params.angular_weight] * 3)
    _, singular_values, vt = np.linalg.svd(jacobian)
    closeness = max(0.0, 1.0 - (singular_values[-1] / params.singular_threshold) ** 2)
    mu = params.damping + params.singular_damping * closeness
    null = (1.0 - closeness) * vt[-1]
    v_posture = params.posture_gain / params.dt * (np.array(params.q_nominal) - q)
    matrix = np.vstack([row_scale[:, None] * jacobian, null, np.sqrt(mu) * np.eye(7)])
    rhs = np.concatenate([row_scale * twist, [null @ v_posture], np.zeros(7)])
    v_limit = params.velocity_scale * kinematics.v_max
    rate = params.position_limit_gain / params.dt
    lower = np.maximum(rate * (kinematics.q_lower + params.position_margin - q), -v_limit)
    upper = np.minimum(rate * (kinematics.q_upper - params.position_margin - q), v_limit)
    return lsq_linear(matrix, rhs, bounds=(lower, upper), method="bvls", tol=1e-14).x


def test_pose_error_of_known_offsets():
    pose = np.eye(4)
    np.testing.assert_array_equal(pose_error(pose, pose), np.zeros(6))
    target = _offset_pose(pose, translation=(0.1, -0.2, 0.3), rpy=(0.0, 0.0, 0.3))
    np.testing.assert_allclose(pose_error(pose, target), [0.1, -0.2, 0.3, 0.0, 0.0, 0.3], atol=1e-15)
    # The rotation part is expressed in world axes: a world-z turn stays a world-z turn.
    rotated = _offset_pose(pose, rpy=(np.pi / 2, 0.0, 0.0))
    np.testing.assert_allclose(pose_error(rotated, _offset_pose(rotated, rpy=(0, 0, 0.2)))[3:], [0, 0, 0.2])


def test_solution_is_the_optimum_of_the_documented_qp(kinematics):
    """Both paths (closed form when no bound binds, OSQP otherwise) against scipy's BVLS."""
    rng = np.random.default_rng(0)
    band = (kinematics.q_lower + 0.05, kinematics.q_upper - 0.05)
    # Tight OSQP tolerances pin down the formulation; the defaults trade accuracy for speed.
    for params, atol in ((DiffIKParams(velocity_scale=0.3, eps_abs=1e-10, eps_rel=1e-10), 1e-7),
                         (DiffIKParams(velocity_scale=0.3), 2e-3)):
        ik = OsqpDifferentialIK(kinematics, params)
        bound_active = 0
        for trial in range(60):
            q = rng.uniform(*band)
            step = 1e-3 if trial % 2 else 0.2  # small steps stay inside the box, large ones hit it
            offsets = rng.uniform(-step, step, (2, 3))
            target = _offset_pose(kinematics.ee_pose(q), offsets[0], offsets[1])
            result = ik.solve(q, target)
            assert result.status is DiffIKStatus.SOLVED
            reference = _reference_velocity(kinematics, params, q, target)
            np.testing.assert_allclose(result.v, reference, atol=atol)
            bound_active += np.any(np.isclose(np.abs(result.v), params.velocity_scale * kinematics.v_max))
        assert 5 < bound_active < 55  # both paths were exercised


def test_error_falls_monotonically_to_reachable_targets(kinematics):
    rng = np.random.default_rng(1)
    ik = OsqpDifferentialIK(kinematics)
    for _ in range(6):
        q_goal = np.clip(HOME + rng.uniform(-0.5, 0.5, 7), kinematics.q_lower + 0.1, kinematics.q_upper - 0.1)
        _, results = _run(ik, HOME, kinematics.ee_pose(q_goal), ticks=600)
        errors = np.array([np.linalg.norm(r.pose_error) for r in results])
        assert np.all(np.diff(errors) <= 1e-8)
        assert errors[-1] < 1e-8


def test_zero_velocity_at_the_target(kinematics):
    ik = OsqpDifferentialIK(kinematics)
    result = ik.solve(HOME, kinematics.ee_pose(HOME))
    assert result.status is DiffIKStatus.SOLVED
    assert np.abs(result.v).max() < 1e-9
    # Away from q_nominal only the posture (null-space) motion may remain: switch it off.
    ik = OsqpDifferentialIK(kinematics, DiffIKParams(posture_gain=0.0))
    q = HOME + np.array([0.3, -0.2, 0.4, 0.3, -0.2, 0.1, 0.5])
    assert np.abs(ik.solve(q, kinematics.ee_pose(q)).v).max() < 1e-9


def test_no_steady_state_error_with_posture_regularisation(kinematics):
    target = _offset_pose(kinematics.ee_pose(HOME), (0.15, 0.1, -0.1), (0.2, -0.1, 0.3))
    postures = {}
    for posture_gain in (0.0, DiffIKParams().posture_gain):
        ik = OsqpDifferentialIK(kinematics, DiffIKParams(posture_gain=posture_gain))
        q, _ = _run(ik, HOME, target, ticks=1500)
        error = pose_error(kinematics.ee_pose(q), target)
        assert np.linalg.norm(error[:3]) < 1e-6 and np.linalg.norm(error[3:]) < 1e-6
        postures[posture_gain] = np.linalg.norm(q - HOME)
    # The posture term was at work: it ends closer to q_nominal than without it.
    assert postures[DiffIKParams().posture_gain] < postures[0.0] - 1e-3


def test_posture_moves_in_the_null_space_while_the_pose_stays(kinematics):
    q = HOME + np.array([0.4, 0.0, -0.4, 0.0, 0.0, 0.0, 0.0])
    target = kinematics.ee_pose(q)
    q, results = _run(OsqpDifferentialIK(kinematics), q, target, ticks=400)
    posture_errors = [np.linalg.norm(r.q_next - HOME) for r in results]
    assert np.all(np.diff(posture_errors) <= 1e-12)
    assert posture_errors[-1] < 0.7 * posture_errors[0]
    assert max(np.linalg.norm(r.pose_error) for r in results) < 1e-4


@pytest.mark.parametrize("preserve_direction", [False, True])
def test_limits_hold_for_thousands_of_random_targets(kinematics, preserve_direction):
    rng = np.random.default_rng(2)
    params = DiffIKParams(preserve_direction=preserve_direction)
    ik = OsqpDifferentialIK(kinematics, params)
    band_low = kinematics.q_lower + params.position_margin
    band_high = kinematics.q_upper - params.position_margin

    def outside(config):
        return np.abs(config - np.clip(config, band_low, band_high))

    for trial in range(2000):
        q = rng.uniform(kinematics.q_lower, kinematics.q_upper)
        target = np.eye(4)
        target[:3, :3] = _random_rotation(rng)
        # Half the targets are poses of the arm, half are anywhere in a 6 m cube (mostly unreachable).
        if trial % 2:
            target[:3, 3] = rng.uniform(-3.0, 3.0, 3)
        else:
            target[:3, 3] = kinematics.ee_pose(rng.uniform(kinematics.q_lower, kinematics.q_upper))[:3, 3]
        result = ik.solve(q, target)
        assert result.status is DiffIKStatus.SOLVED
        _assert_safe(kinematics, params, q, result)
        # Inside the margin band it stays inside; outside it, it never moves further out.
        assert np.all(outside(result.q_next) <= outside(q) + LIMIT_TOL)


@pytest.mark.parametrize("position", [(2.0, 1.0, 0.5), (0.0, 0.0, 2.0), (-1.5, 0.2, 0.3), (0.3, -2.0, 0.1)])
def test_unreachable_targets_settle_at_bounded_velocity(kinematics, position):
    params = DiffIKParams()
    target = kinematics.ee_pose(HOME)
    target[:3, 3] = position
    ik = OsqpDifferentialIK(kinematics, params)
    q = HOME
    errors, speeds = [], []
    for _ in range(1500):
        result = ik.solve(q, target)
        assert result.ok
        _assert_safe(kinematics, params, q, result)
        q = result.q_next
        errors.append(np.linalg.norm(result.pose_error[:3]))
        speeds.append(np.abs(result.v).max())
    assert max(speeds[-300:]) < 0.02  # it has come to rest ...
    assert errors[-1] < min(errors) + 0.01  # ... at (nearly) the closest pose it passed
    assert errors[-1] < errors[0] - 0.2


@pytest.mark.parametrize(
    "q_start",
    [
        np.array([0.0, 0.3, 0.0, -0.08, 0.0, 1.6, 0.785]),  # fully stretched elbow (q4 at its limit)
        np.array([0.0, 0.0, 0.0, -0.08, 0.0, 0.0, 0.0]),  # stretched and pointing straight up
        np.array([1.94, -0.015, 0.967, -0.416, 1.435, 1.299, -0.805]),  # smallest singular value 1.4e-4
    ],
)
def test_near_singular_configurations_give_bounded_output(kinematics, q_start):
    params = DiffIKParams()
    ik = OsqpDifferentialIK(kinematics, params)
    start_pose = kinematics.ee_pose(q_start)
    for translation in [(0.3, 0.0, 0.0), (0.0, 0.0, 0.3), (0.0, 0.2, 0.0), (-0.2, 0.0, -0.2)]:
        target = _offset_pose(start_pose, translation, (0.3, 0.0, -0.3))
        q = q_start
        for _ in range(200):
            result = ik.solve(q, target)
            assert result.ok
            _assert_safe(kinematics, params, q, result)
            q = result.q_next


def test_a_failed_osqp_run_is_solved_exactly_by_active_sets(kinematics):
    # A slow velocity limit makes the bounds bind, so the tick needs OSQP; one iteration cannot converge. The box QP
    # is then solved by `solve_box_qp`: the same answer as OSQP given the iterations it needs.
    params = DiffIKParams(velocity_scale=0.05, max_iter=1)
    target = _offset_pose(kinematics.ee_pose(HOME), (0.2, 0.0, 0.0))
    result = OsqpDifferentialIK(kinematics, params).solve(HOME, target)
    converged = OsqpDifferentialIK(kinematics, dataclasses.replace(params, max_iter=20000)).solve(HOME, target)
    assert result.status is DiffIKStatus.SOLVED and converged.status is DiffIKStatus.SOLVED
    np.testing.assert_allclose(result.v, converged.v, atol=1e-9)
    assert np.abs(result.v).max() > 0.01


def test_badly_scaled_weights_do_not_freeze_the_arm(kinematics, monkeypatch):
    """With a large angular weight OSQP fails some ticks for good (the same problem returns the next tick, so a hold
    would freeze the arm); the active-set solve answers them all."""
    import trivla_drake.robot.osqp_diffik as diffik

    def problems():
        rng = np.random.default_rng(5)
        for i in range(300):
            q = rng.uniform(kinematics.q_lower, kinematics.q_upper)
            if i % 3 == 0:
                q[3] = rng.uniform(kinematics.q_upper[3] - 0.05, kinematics.q_upper[3])
                q[5] = rng.uniform(-0.0175, 0.05)
            target = np.eye(4)
            target[:3, :3] = pin.Quaternion(rng.normal(size=4)).normalized().matrix()
            target[:3, 3] = rng.uniform(-2, 2, 3)
            yield q, target

    params = DiffIKParams(angular_weight=100.0)
    real = diffik.solve_box_qp
    monkeypatch.setattr(diffik, "solve_box_qp", lambda *args, **kwargs: None)
    ik = OsqpDifferentialIK(kinematics, params)
    hard = [(q, target) for q, target in problems() if not ik.solve(q, target).ok]
    if not hard:
        pytest.skip("this OSQP build converges on every problem: nothing for the fallback to answer")
    held = ik.solve(*hard[0])
    assert held.status is DiffIKStatus.SOLVER_FAILED and not held.v.any()  # the hold without the fallback
    monkeypatch.setattr(diffik, "solve_box_qp", real)
    for q, target in hard:
        result = ik.solve(q, target)
        assert result.status is DiffIKStatus.SOLVED and np.abs(result.v).max() > 1e-3
        _assert_safe(kinematics, params, q, result)


def test_box_qp_meets_the_kkt_conditions_on_random_problems():
    from trivla_drake.robot.osqp_diffik import solve_box_qp

    rng = np.random.default_rng(0)
    for _ in range(200):
        a = rng.normal(size=(7, 7))
        hessian, gradient = a @ a.T + 0.01 * np.eye(7), 5 * rng.normal(size=7)
        lower, upper = -rng.uniform(0.1, 1.0, 7), rng.uniform(0.1, 1.0, 7)
        x = solve_box_qp(hessian, gradient, lower, upper, rng.uniform(lower, upper))
        assert x is not None and (lower <= x).all() and (x <= upper).all()
        residual = hessian @ x + gradient
        inside = (x > lower + 1e-12) & (x < upper - 1e-12)
        np.testing.assert_allclose(residual[inside], 0.0, atol=1e-8)
        assert (residual[x <= lower + 1e-12] >= -1e-8).all() and (residual[x >= upper - 1e-12] <= 1e-8).all()


def test_solver_failure_returns_a_hold(kinematics, monkeypatch):
    import trivla_drake.robot.osqp_diffik as diffik

    params = DiffIKParams(velocity_scale=0.05, max_iter=1000)
    target = _offset_pose(kinematics.ee_pose(HOME), (0.2, 0.0, 0.0))
    # An infeasible answer comes back as huge numbers, not NaN: it must not leak out, and when the active-set
    # solve fails too the tick holds.
    ik = OsqpDifferentialIK(kinematics, params)
    real_solve, real_box = ik._solver.solve, diffik.solve_box_qp
    infeasible = SimpleNamespace(
        x=np.full(7, 1e9), info=SimpleNamespace(status_val=osqp.SolverStatus.OSQP_PRIMAL_INFEASIBLE)
    )
    monkeypatch.setattr(ik._solver, "solve", lambda **kwargs: infeasible)
    monkeypatch.setattr(diffik, "solve_box_qp", lambda *args, **kwargs: None)
    result = ik.solve(HOME, target)
    assert result.status is DiffIKStatus.SOLVER_FAILED and not result.ok
    np.testing.assert_array_equal(result.v, np.zeros(7))
    np.testing.assert_array_equal(result.q_next, HOME)
    np.testing.assert_allclose(result.pose_error[:3], [0.2, 0.0, 0.0], atol=1e-12)
    # With the active-set solve the same tick moves; the next healthy OSQP tick as well.
    monkeypatch.setattr(diffik, "solve_box_qp", real_box)
    assert ik.solve(HOME, target).status is DiffIKStatus.SOLVED
    monkeypatch.setattr(ik._solver, "solve", real_solve)
    result = ik.solve(HOME, target)
    assert result.status is DiffIKStatus.SOLVED and np.abs(result.v).max() > 0.01


@pytest.mark.parametrize(
    "edit, match",
    [
        (lambda pose: pose.__setitem__((0, 3), np.nan), "target_pose contains NaN/inf"),
        (lambda pose: pose.__setitem__((1, 1), np.inf), "target_pose contains NaN/inf"),
        (lambda pose: pose.__setitem__((slice(0, 3), slice(0, 3)), 2 * np.eye(3)), "rotation matrix"),
        (lambda pose: pose.__setitem__((slice(0, 3), slice(0, 3)), -np.eye(3)), "rotation matrix"),
    ],
)
def test_bad_targets_raise_naming_target_pose(kinematics, edit, match):
    target = kinematics.ee_pose(HOME)
    edit(target)
    with pytest.raises(ValueError, match=match):
        OsqpDifferentialIK(kinematics).solve(HOME, target)
    with pytest.raises(ValueError, match="target_pose must be a 4x4"):
        OsqpDifferentialIK(kinematics).solve(HOME, np.eye(3))


def test_bad_configuration_raises_naming_q(kinematics):
    q = HOME.copy()
    q[2] = np.nan
    with pytest.raises(ValueError, match="q contains NaN/inf"):
        OsqpDifferentialIK(kinematics).solve(q, kinematics.ee_pose(HOME))


@pytest.mark.parametrize(
    "field, value",
    [
        ("gain", 0.0),
        ("velocity_scale", 1.5),
        ("dt", -0.01),
        ("damping", -1.0),
        ("max_iter", 0),
        ("q_nominal", (0.0,) * 6),
    ],
)
def test_bad_params_raise_naming_the_field(kinematics, field, value):
    with pytest.raises(ValueError, match=field):
        OsqpDifferentialIK(kinematics, DiffIKParams(**{field: value}))


def test_results_do_not_alias_inputs_or_each_other(kinematics):
    ik = OsqpDifferentialIK(kinematics, DiffIKParams(velocity_scale=0.05))  # the OSQP path
    q = HOME.copy()
    target = _offset_pose(kinematics.ee_pose(HOME), (0.2, 0.0, 0.0))
    first = ik.solve(q, target)
    saved = first.v.copy(), first.q_next.copy()
    ik.solve(first.q_next, _offset_pose(target, (-0.4, 0.1, 0.0)))
    np.testing.assert_array_equal(q, HOME)
    np.testing.assert_array_equal(first.v, saved[0])
    np.testing.assert_array_equal(first.q_next, saved[1])


def test_answer_does_not_depend_on_earlier_ticks():
    """Two Drake Contexts share one solver: a tick's answer must be a function of (q, target) only."""
    kinematics = PandaKinematics()
    fresh, used = OsqpDifferentialIK(kinematics), OsqpDifferentialIK(kinematics)
    rng = np.random.default_rng(3)
    for _ in range(30):  # give `used` a history of its own
        used.solve(rng.uniform(kinematics.q_lower, kinematics.q_upper),
                   kinematics.ee_pose(rng.uniform(kinematics.q_lower, kinematics.q_upper)))
    active = 0
    for _ in range(40):  # far targets: velocity bounds are active, so OSQP runs
        q = rng.uniform(kinematics.q_lower + 0.3, kinematics.q_upper - 0.3)
        target = kinematics.ee_pose(rng.uniform(kinematics.q_lower, kinematics.q_upper))
        a, b = fresh.solve(q, target), used.solve(q, target)
        active += bool(np.any(np.isclose(np.abs(a.v), 0.5 * kinematics.v_max)))
        np.testing.assert_array_equal(a.v, b.v)
    assert active > 10


def _largest_off_line_deviation(kinematics, params, q0, action, seconds=0.6):
    """The hand's largest distance [m] from the straight line of a constant action, played at 36 Hz through
    `apply_action` and tracked at the diff-IK's rate (kinematics only: q integrates the answers)."""
    from trivla_drake.systems.action_executor import apply_action

    ik = OsqpDifferentialIK(kinematics, params)
    q, target = np.array(q0, float), kinematics.ee_pose(q0)
    start = target[:3, 3].copy()
    direction = np.asarray(action[:3], float) / np.linalg.norm(action[:3])
    next_action, deviation = 0.0, 0.0
    for tick in range(int(seconds / params.dt)):
        while next_action <= tick * params.dt + 1e-12:
            target, _ = apply_action(target, np.asarray(action, float))
            next_action += 1.0 / 36.0
        result = ik.solve(q, target)
        _assert_safe(kinematics, params, q, result)
        q = result.q_next
        moved = kinematics.ee_pose(q)[:3, 3] - start
        deviation = max(deviation, float(np.linalg.norm(moved - (moved @ direction) * direction)))
    return deviation


@pytest.mark.parametrize("q0, action", [
    ((0.0, -0.3, 0.0, -2.2, 0.0, 1.9, 0.785), (0.005, 0.0, -0.005, 0.025, 0.025, 0.0, 1.0)),
    ((0.0, -0.3, 0.0, -2.2, 0.0, 1.9, 0.785), (0.01, 0.0, -0.01, 0.05, 0.05, 0.0, 1.0)),
])
def test_preserve_direction_keeps_the_hand_on_the_commanded_line(kinematics, q0, action):
    """With the velocity bounds binding, the least-squares QP trades translation against rotation and the hand
    leaves the line by centimetres; scaling the whole twist keeps it within a millimetre."""
    default = _largest_off_line_deviation(kinematics, DiffIKParams(), q0, action)
    kept = _largest_off_line_deviation(kinematics, DiffIKParams(preserve_direction=True), q0, action)
    assert default > 0.01 and kept < 0.002, (default, kept)


def test_preserve_direction_changes_nothing_while_no_bound_binds(kinematics):
    target = _offset_pose(kinematics.ee_pose(HOME), (0.002, 0.0, 0.0))
    plain = OsqpDifferentialIK(kinematics, DiffIKParams()).solve(HOME, target)
    kept = OsqpDifferentialIK(kinematics, DiffIKParams(preserve_direction=True)).solve(HOME, target)
    np.testing.assert_array_equal(plain.v, kept.v)
