"""Differential inverse kinematics for the Panda as a small QP solved by OSQP each controller tick.

Per tick, with J the 6x7 end-effector Jacobian at q (LOCAL_WORLD_ALIGNED, rows [v; w]):

    min_v  |J v - V_des|^2_W  +  |N (v - v_posture)|^2  +  mu |v|^2
    s.t.   max(-s v_max, g (q_lower + m - q) / dt)  <=  v  <=  min(s v_max, g (q_upper - m - q) / dt)

V_des = gain * pose_error / dt with each part capped at a maximum speed; W weighs rotation against
translation; v_posture = posture_gain * (q_nominal - q) / dt; N = n n^T projects onto J's null space
(n its unit null vector), so the posture term cannot fight the task and leaves no steady-state pose
error; mu is a Levenberg-Marquardt damping that grows as J's smallest singular value falls below a
threshold (where the posture term fades out); s, g, m are velocity_scale, position_limit_gain and
position_margin. q_next = q + dt v.

The constraints are a box, so when the unconstrained minimiser (one Cholesky solve) lies inside it,
it is the QP's optimum and OSQP is skipped; OSQP, set up once and warm-started, handles the ticks
where a bound binds.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import numpy as np
import osqp
import pinocchio as pin
import scipy.sparse as sp
from scipy.linalg.lapack import dgesvd, dposv

from trivla_drake.robot.panda_kinematics import PandaKinematics

PANDA_HOME = (0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785)
_IDENTITY3 = np.eye(3)


@dataclass
class DiffIKParams:
    """Settings of `OsqpDifferentialIK`; every default suits the simulated Panda at 100 Hz."""

    # Controller tick [s]: the QP's velocities are integrated over it, q_next = q + dt v.
    dt: float = 0.01
    # Fraction of the pose error the commanded twist removes in one tick [-], in (0, 1].
    gain: float = 1.0
    # Cap on the commanded linear speed of the end effector [m/s].
    max_linear_speed: float = 0.5
    # Cap on the commanded angular speed of the end effector [rad/s].
    max_angular_speed: float = 1.5
    # Weight of the rotation rows of the task against the translation rows [m^2/rad^2]; it only
    # matters when the target cannot be reached exactly (limits, singularities).
    angular_weight: float = 1.0
    # Fraction of the posture error (q_nominal - q) the null-space motion removes per tick [-].
    posture_gain: float = 0.01
    # Posture the redundant (null-space) degree of freedom is pulled towards [rad].
    q_nominal: tuple[float, ...] = PANDA_HOME
    # Fraction of the URDF velocity limits the solution may use [-], in (0, 1].
    velocity_scale: float = 0.5
    # Distance kept from each URDF position limit [rad].
    position_margin: float = 0.01
    # Fraction of the remaining distance to a position limit one tick may cover [-], in (0, 1];
    # below 1 the arm slows down as it nears a limit instead of stopping in a single tick.
    position_limit_gain: float = 0.5
    # Constant Levenberg-Marquardt damping mu on |v|^2 [units of J^T J].
    damping: float = 1e-6
    # Extra damping reached when J's smallest singular value is zero [units of J^T J].
    singular_damping: float = 2.5e-3
    # Smallest singular value of J below which the extra damping ramps in and the posture term
    # fades out, both quadratically in the singular value [units of J].
    singular_threshold: float = 0.05
    # OSQP absolute and relative tolerances, for ticks where a bound binds; the velocity is then
    # accurate to about eps over P's smallest eigenvalue (ticks with no bound active are exact).
    eps_abs: float = 1e-6
    eps_rel: float = 1e-6
    # OSQP iteration cap; a tick that hits it is solved exactly by active sets (`solve_box_qp`) instead, and
    # holds position only if that fails too.
    max_iter: int = 1000
    # When a velocity or position bound binds: False (the default, the demonstrations' controller) solves the
    # bounded least-squares QP, which may trade the translation against the rotation, so the hand leaves the
    # straight line to a far target (up to a few cm at the actions' top speed); True scales the whole desired
    # twist down until the unbounded answer fits the bounds (as Drake's DoDifferentialInverseKinematics keeps the
    # direction), and falls back to the QP only where even a still twist does not fit (the posture term against
    # a position limit) or the scale would be about 0.
    preserve_direction: bool = False


class DiffIKStatus(enum.Enum):
    """Outcome of one `OsqpDifferentialIK.solve` tick."""

    SOLVED = "solved"
    # OSQP stopped short of its tolerances; the velocity is still clipped into the joint limits.
    SOLVED_INACCURATE = "solved_inaccurate"
    # A failed SVD, or an OSQP failure (iteration cap, infeasible, ...) the active-set solve could not answer
    # either: the tick holds, v = 0.
    SOLVER_FAILED = "solver_failed"


@dataclass(frozen=True)
class DiffIKResult:
    """One tick's answer: the next joint position and the velocity that leads there."""

    q_next: np.ndarray  # q + dt v [rad], shape (7,)
    v: np.ndarray  # joint velocity [rad/s], shape (7,)
    status: DiffIKStatus
    pose_error: np.ndarray  # `pose_error(X_current, X_target)` before the step, shape (6,)

    @property
    def ok(self) -> bool:
        """True when the QP produced a motion (solved, possibly inaccurately); False for a hold."""
        return self.status is not DiffIKStatus.SOLVER_FAILED


def pose_error(X_current: np.ndarray, X_target: np.ndarray) -> np.ndarray:
    """6-D error [p_target - p; log3(R_target R^T)] between two 4x4 poses, in world axes [m; rad].

    It is the twist (order [v; w], LOCAL_WORLD_ALIGNED) that moves X_current onto X_target in unit
    time, the translation taken at the frame origin.
    """
    error = np.empty(6)
    error[:3] = X_target[:3, 3] - X_current[:3, 3]
    error[3:] = pin.log3(X_target[:3, :3] @ X_current[:3, :3].T)
    return error


def _clip_norm(x: np.ndarray, max_norm: float) -> None:
    """Scale `x` in place so that its norm is at most `max_norm`, keeping its direction."""
    norm = math.sqrt(x @ x)
    if norm > max_norm:
        x *= max_norm / norm


class OsqpDifferentialIK:
    """Joint-velocity differential IK: one small QP per `solve(q, target_pose)` call (module docstring).

    The OSQP problem's sparsity is fixed in __init__ (dense upper-triangular P, identity A), so a
    tick only rewrites P's values and the vectors q, l, u. Not thread-safe: it owns solver and
    kinematics state.
    """

    def __init__(self, kinematics: PandaKinematics, params: DiffIKParams | None = None) -> None:
        self.kinematics = kinematics
        self.params = params = params or DiffIKParams()
        n = kinematics.nq
        self._q_nominal = np.asarray(params.q_nominal, dtype=float)
        _check_params(params, self._q_nominal, kinematics)
        self._v_limit = params.velocity_scale * kinematics.v_max
        # Row 0: lower position limits, row 1: upper ones, each moved inwards by the margin.
        self._q_limits = np.stack(
            [kinematics.q_lower + params.position_margin, kinematics.q_upper - params.position_margin]
        )
        self._limit_rate = params.position_limit_gain / params.dt
        self._row_scale = np.sqrt([1.0, 1.0, 1.0] + [params.angular_weight] * 3)
        self._row_scale_column = self._row_scale[:, None]

        # The cost is |rows v - rhs|^2 + mu |v|^2, i.e. P = rows^T rows + mu I and q = -rows^T rhs;
        # these buffers are rewritten every tick. rhs is stored negated so that q is one product.
        self._rows = np.empty((6 + 1, n))  # [sqrt(W) J; null^T]: six task rows, one posture row
        self._neg_rhs = np.empty(6 + 1)  # -[sqrt(W) V_des; null . v_posture]
        self._hessian = np.empty((n, n))
        self._hessian_diagonal = self._hessian.reshape(-1)[:: n + 1]  # a view
        self._gradient = np.empty(n)
        self._split_gradient = np.empty((n, 2), order="F")  # the twist rows' and the posture row's parts
        self._bounds = np.empty((2, n))  # [l; u] of the QP

        # P's values are passed as its upper triangle in CSC order (column by column, rows 0..j):
        # the row-major lower triangle, transposed, enumerates exactly that.
        cols, rows = np.tril_indices(n)
        self._triu_flat = rows * n + cols
        pattern = sp.csc_matrix((np.ones(rows.size), (rows, cols)), shape=(n, n))
        self._rho = 0.1  # OSQP's default initial step size; reset before every run
        self._zero_dual = np.zeros(n)
        self._solver = osqp.OSQP()
        # OSQP keeps (and later overwrites) the matrices given to setup(): hand it fresh ones.
        self._solver.setup(
            P=pattern,
            q=np.zeros(n),
            A=sp.identity(n, format="csc"),
            l=-self._v_limit,
            u=self._v_limit.copy(),
            verbose=False,
            # Polishing prints to stdout from C; the final clip into the box replaces it.
            polishing=False,
            warm_starting=True,
            rho=self._rho,
            eps_abs=params.eps_abs,
            eps_rel=params.eps_rel,
            max_iter=params.max_iter,
        )

    def solve(self, q: np.ndarray, target_pose: np.ndarray) -> DiffIKResult:
        """One controller tick: the joint velocity moving the end effector at q towards target_pose.

        Raises ValueError when q is not a finite 7-vector or target_pose not a finite 4x4 rigid
        transform; a failed QP returns a hold (v = 0, q_next = q) with status SOLVER_FAILED.
        """
        target_pose = _check_target_pose(target_pose)
        p = self.params
        pose, jacobian = self.kinematics.forward(q)
        q = np.asarray(q, dtype=float)
        error = pose_error(pose, target_pose)

        # V_des (negated) = -gain * error / dt, each part capped at its maximum speed.
        neg_twist = self._neg_rhs[:6]
        np.multiply(error, -p.gain / p.dt, out=neg_twist)
        _clip_norm(neg_twist[:3], p.max_linear_speed)
        _clip_norm(neg_twist[3:], p.max_angular_speed)
        neg_twist *= self._row_scale
        np.multiply(jacobian, self._row_scale_column, out=self._rows[:6])

        # The last right singular vector spans J's null space (J is 6x7), and |N x|^2 = (null . x)^2,
        # so the projected posture term is one more least-squares row. Below the singular threshold
        # the damping ramps in and the posture row fades out: there the two smallest singular
        # directions trade places from tick to tick, and posture motion along either one chatters.
        _, singular_values, vt, info = dgesvd(jacobian)
        if info != 0:
            return self._hold(q, error)
        closeness = max(0.0, 1.0 - (singular_values[-1] / p.singular_threshold) ** 2)  # 0 far, 1 at it
        mu = p.damping + p.singular_damping * closeness
        posture_weight = 1.0 - closeness
        np.multiply(vt[-1], posture_weight, out=self._rows[6])
        self._neg_rhs[6] = (posture_weight * p.posture_gain / p.dt) * (vt[-1] @ (q - self._q_nominal))

        np.matmul(self._rows.T, self._rows, out=self._hessian)
        self._hessian_diagonal += mu
        np.matmul(self._neg_rhs, self._rows, out=self._gradient)

        bounds = self._bounds
        np.subtract(self._q_limits, q, out=bounds)
        bounds *= self._limit_rate
        # np.clip is several times slower than this pair on 7-vectors.
        np.maximum(bounds, -self._v_limit, out=bounds)
        np.minimum(bounds, self._v_limit, out=bounds)

        # The only constraints are a box: when the unconstrained minimiser (one Cholesky solve) lies
        # inside it, it is the QP's optimum (all multipliers zero), exact rather than to OSQP's
        # tolerance, so OSQP only runs on ticks where a bound is active.
        _, v, info = dposv(self._hessian, -self._gradient)
        if info == 0 and (bounds[0] <= v).all() and (v <= bounds[1]).all():
            return DiffIKResult(q + p.dt * v, v, DiffIKStatus.SOLVED, error)
        if info == 0 and p.preserve_direction:
            scaled = self._scaled_twist_velocity(bounds)
            if scaled is not None:
                return DiffIKResult(q + p.dt * scaled, scaled, DiffIKStatus.SOLVED, error)

        self._solver.update(
            Px=self._hessian.take(self._triu_flat), q=self._gradient, l=bounds[0], u=bounds[1]
        )
        # Start every OSQP run from the same point for the same problem: the clipped unconstrained
        # minimiser (close to the optimum), zero multipliers and the initial step size. The answer
        # is then a function of (q, target_pose) alone, not of earlier ticks, so two simulations
        # sharing this solver (two Drake Contexts) give bit-identical results.
        if info != 0:
            v = np.zeros_like(q)
        np.maximum(v, bounds[0], out=v)
        np.minimum(v, bounds[1], out=v)
        self._solver.update_settings(rho=self._rho)
        self._solver.warm_start(x=v, y=self._zero_dual)
        result = self._solver.solve(raise_error=False)

        status_val = result.info.status_val
        if status_val == osqp.SolverStatus.OSQP_SOLVED:
            status = DiffIKStatus.SOLVED
        elif status_val == osqp.SolverStatus.OSQP_SOLVED_INACCURATE:
            status = DiffIKStatus.SOLVED_INACCURATE
        else:
            # OSQP ran out of iterations (it can on badly scaled weights, and the same problem comes back next
            # tick): the box QP in 7 variables is solved exactly by active sets instead; a hold only if that fails.
            v = solve_box_qp(self._hessian, self._gradient, bounds[0], bounds[1], v)
            if v is None:
                return self._hold(q, error)
            return DiffIKResult(q + p.dt * v, v, DiffIKStatus.SOLVED, error)
        v = self._polish(result.x, bounds)
        return DiffIKResult(q + p.dt * v, v, status, error)

    def _scaled_twist_velocity(self, bounds: np.ndarray) -> np.ndarray | None:
        """The unbounded minimiser with the desired twist scaled by the largest alpha in [0, 1] that fits the box:
        v(alpha) = alpha a + b is affine (a from the twist rows, b from the posture row), so a ratio test over the
        joints finds alpha. None when b alone leaves the box or alpha is about 0 (the caller then solves the QP)."""
        rhs = self._split_gradient
        np.matmul(self._neg_rhs[:6], self._rows[:6], out=rhs[:, 0])
        np.multiply(self._rows[6], self._neg_rhs[6], out=rhs[:, 1])
        _, ab, info = dposv(self._hessian, -rhs)
        if info != 0:
            return None
        a, b = ab[:, 0], ab[:, 1]
        if (b < bounds[0]).any() or (b > bounds[1]).any():
            return None
        with np.errstate(divide="ignore", invalid="ignore"):
            limits = np.where(a > 0, (bounds[1] - b) / a, np.where(a < 0, (bounds[0] - b) / a, np.inf))
        alpha = min(1.0, float(limits.min()))
        if alpha < 1e-3:
            return None
        return np.minimum(np.maximum(alpha * a + b, bounds[0]), bounds[1])  # the clip only removes rounding

    def _polish(self, x: np.ndarray, bounds: np.ndarray) -> np.ndarray:
        """The exact optimum on the active set OSQP found (what OSQP's own polishing does, silently).

        ADMM meets the bounds only to within its tolerance, and its last digits depend on the
        solver's history (in-place KKT updates), which two Drake Contexts sharing this solver must
        not see. Fixing the active bounds and solving the free joints' normal equations exactly
        removes both. If the active set fails the optimality check, the clipped iterate is kept.
        """
        scale = np.maximum(1.0, np.abs(bounds))
        at_lower = x <= bounds[0] + 1e-4 * scale[0]
        at_upper = x >= bounds[1] - 1e-4 * scale[1]
        v = np.where(at_lower, bounds[0], np.where(at_upper, bounds[1], x))
        free = ~(at_lower | at_upper)
        if free.any():
            fixed = ~free
            rhs = -(self._gradient[free] + self._hessian[np.ix_(free, fixed)] @ v[fixed])
            _, v_free, info = dposv(self._hessian[np.ix_(free, free)], rhs)
            if info != 0 or (v_free < bounds[0][free]).any() or (v_free > bounds[1][free]).any():
                return np.minimum(np.maximum(x, bounds[0]), bounds[1])
            v[free] = v_free
        # Multipliers of the active bounds must push inwards (KKT), else the set was wrong.
        residual = self._hessian @ v + self._gradient
        if (residual[at_lower] < -1e-9).any() or (residual[at_upper] > 1e-9).any():
            return np.minimum(np.maximum(x, bounds[0]), bounds[1])
        return v

    @staticmethod
    def _hold(q: np.ndarray, error: np.ndarray) -> DiffIKResult:
        """The answer of a failed tick: stay at q."""
        return DiffIKResult(q.copy(), np.zeros_like(q), DiffIKStatus.SOLVER_FAILED, error)


def solve_box_qp(hessian: np.ndarray, gradient: np.ndarray, lower: np.ndarray, upper: np.ndarray,
                 start: np.ndarray, max_rounds: int = 100) -> np.ndarray | None:
    """The minimiser of 1/2 x'Hx + g'x over lower <= x <= upper (H positive definite) by a primal active-set
    method from `start`: solve for the free variables with the others at their bounds; put any that leave the box on
    their bound; release the bound whose multiplier pushes outwards the most; stop when the KKT conditions hold.
    None if it has not converged within `max_rounds` (or a reduced system is not positive definite)."""
    x = np.minimum(np.maximum(start, lower), upper)
    at_lower, at_upper = x <= lower, x >= upper
    for _ in range(max_rounds):
        free = ~(at_lower | at_upper)
        x = np.where(at_lower, lower, np.where(at_upper, upper, x))
        if free.any():
            fixed = ~free
            rhs = -(gradient[free] + hessian[np.ix_(free, fixed)] @ x[fixed])
            _, x_free, info = dposv(hessian[np.ix_(free, free)], rhs)
            if info != 0:
                return None
            below, above = x_free < lower[free], x_free > upper[free]
            if below.any() or above.any():
                at_lower[np.flatnonzero(free)[below]] = True
                at_upper[np.flatnonzero(free)[above]] = True
                continue
            x[free] = x_free
        # The multipliers of the bounds: at a lower bound the gradient must point inwards (>= 0), at an upper one
        # outwards-negative (<= 0). Release the worst offender, if any.
        residual = hessian @ x + gradient
        wrong = np.where(at_lower, -residual, 0.0) + np.where(at_upper, residual, 0.0)
        worst = int(np.argmax(wrong))
        if wrong[worst] <= 1e-9 * max(1.0, float(np.abs(residual).max())):
            return x
        at_lower[worst] = at_upper[worst] = False
    return None


def _check_target_pose(target_pose: np.ndarray) -> np.ndarray:
    """Return target_pose as a float 4x4 array; ValueError naming it unless it is a finite rigid transform."""
    target_pose = np.asarray(target_pose, dtype=float)
    if target_pose.shape != (4, 4):
        raise ValueError(f"target_pose must be a 4x4 homogeneous matrix, got shape {target_pose.shape}")
    if not np.isfinite(target_pose).all():
        raise ValueError("target_pose contains NaN/inf")
    rotation = target_pose[:3, :3]
    deviation = rotation.T @ rotation - _IDENTITY3
    (a, b, c), (d, e, f), (g, h, i) = rotation.tolist()
    # Written out because np.linalg.det costs more than the whole rest of this check.
    determinant = a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)
    # 1e-10 on the squared deviation admits rotations that went through float32 (about 1e-7 off).
    if (deviation * deviation).sum() > 1e-10 or determinant < 0.0:
        raise ValueError(
            f"target_pose[:3, :3] must be a rotation matrix (orthonormal, det +1), got {rotation.tolist()}"
        )
    return target_pose


def _check_params(params: DiffIKParams, q_nominal: np.ndarray, kinematics: PandaKinematics) -> None:
    """Raise ValueError naming the first field of `params` outside its accepted range."""
    if q_nominal.shape != (kinematics.nq,):
        raise ValueError(f"q_nominal must have {kinematics.nq} entries, got {q_nominal.shape}")
    for name in ("gain", "velocity_scale", "position_limit_gain"):
        value = getattr(params, name)
        if not 0.0 < value <= 1.0:
            raise ValueError(f"{name} must be in (0, 1], got {value}")
    for name in (
        "dt", "max_linear_speed", "max_angular_speed", "angular_weight", "singular_threshold", "max_iter"
    ):
        value = getattr(params, name)
        if not value > 0.0:
            raise ValueError(f"{name} must be positive, got {value}")
    for name in ("posture_gain", "position_margin", "damping", "singular_damping", "eps_abs", "eps_rel"):
        value = getattr(params, name)
        if not value >= 0.0:
            raise ValueError(f"{name} must be non-negative, got {value}")
    if 2 * params.position_margin >= np.min(kinematics.q_upper - kinematics.q_lower):
        raise ValueError(f"position_margin {params.position_margin} leaves no room between the joint limits")
