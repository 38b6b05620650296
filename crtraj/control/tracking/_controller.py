"""Tracking controller: planned configurations -> rate-limited actuator commands.

The paper's proportional law (eq. 15-16), ``q_dot = J^+ (Phi_d_dot + K_P e)``,
in crtraj's variables: the configuration error ``e = x_ref - x`` (bending
vectors in rad, base translation z in mm) is turned into an actuator increment
through the cable Jacobian ``J_q = dq/dx`` (`Model.jac_cables`, the paper's
``J_Phi^+``: q = q0 + A x is linear, so ``J_q = A`` everywhere).

K_P is designed with python-control, not guessed. Design model (per control
period dt, exact zero-order-hold discretisation):

* each actuator is a position servo with a first-order lag,
  ``tau dq/dt = q_cmd - q`` (tau = ``servo_tau`` for the cables,
  ``servo_tau_z`` for the base stage). All cables of a segment share tau, so in
  configuration coordinates the servos are ``tau_j dx_j/dt = x_cmd,j - x_j``
  exactly; ``control.c2d`` gives ``x[k+1] = Phi x[k] + Gamma x_cmd[k]`` with
  ``Phi = exp(-dt/tau)``, ``Gamma = 1 - Phi``.
* the controller holds a set-point and changes it by ``v[k]`` per period (the
  paper's ``q_dot ~ Delta q``): ``x_cmd[k] = x_cmd[k-1] + v[k]``.
* for a constant reference r the error state ``e = (r - x[k], r - x_cmd[k-1])``
  (2 nx) follows ``e[k+1] = A e[k] - B v[k]`` with ``A = [[Phi, Gamma], [0, I]]``,
  ``B = [[Gamma], [I]]``; ``control.dlqr`` on (A, B, Q, R) gives
  ``v = K e = K_x (r - x) + K_c (r - x_cmd)``. With no servo lag the two blocks
  act on the same error, so ``K_P = K_x + K_c`` is the paper's symmetric
  positive-definite proportional gain (diagonal here, since every coordinate's
  dynamics are decoupled).
* with the planned rate ``x_reference_rate`` (paper eq. 15) the increment also
  gets ``dt * x_ref_dot`` and the set-point leads the reference by
  ``phi / (1 - phi)`` periods of motion, which is exactly the servo's lag on a
  ramp: a constant-rate reference is then tracked with zero steady error
  (without the rate, eq. 16, a ramp leaves a steady lag).
* weights by Bryson's rule: Q penalises the configuration error with scale
  ``bending_error_scale`` (rad) / ``z_error_scale`` (mm); R penalises the
  per-period increment relative to the largest increment the rate limits allow
  (``max_cable_rate dt / cable_radius`` rad, ``max_z_rate dt`` mm), times
  ``effort_weight``.

Commands are then rate-limited (every actuator's change per period at most
``max_rate * dt``, by scaling the whole increment so the motion keeps its
direction) and kept inside the robot's actuation limits (cable strokes,
theta_max, z stroke): a command never leaves the feasible set, and a set-point
that is already outside is never moved further out.

With the robot's actuator limits (`RateLimits`, J = d actuator value / d x) the
set-point also keeps ``|J v| <= vmax h`` and ``|J (v - v_prev)| <= amax h^2`` per
period h (v_prev: the previous period's increment): the increment is first scaled
to the speed limits, then moved from v_prev toward that only as far as the
acceleration limits allow (a convex combination of two speed-feasible increments
is speed-feasible). The first-order servos average the set-point staircase with
a positive kernel of unit mass, so the actual actuator motion sampled at any
multiple of h has finite-difference speed and acceleration within the same limits.
The actuation-limit shrink comes last and may brake harder (limits win).

``mode = "tip"`` adds the paper's eq. 13 and 17: the measured tip error is
mapped to a configuration error with the damped least-squares pseudo-inverse
of the task Jacobian ``J = d tip/dx`` (damping lambda), and the rest of the
configuration error is kept in J's null space, so a tip sensor (motion
capture) corrects model error while the body still follows the planned,
collision-free configuration.

Units: mm, rad, s. The controller is stateless: the caller owns the actuator
set-point (``q_command``) and passes it back each period.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import casadi as ca
import numpy as np

from crtraj.control.tracking._design import TrackingDesign, lqr_design
from crtraj.control.tracking._limits import ActuationLimits, accelerate, braking
from crtraj.control.tracking._options import TrackingOptions
from crtraj.control.tracking._servo import MAX_PERIODS, ServoModel
from crtraj.core.errors import InputError
from crtraj.core.fields import check_float
from crtraj.model.kinematics import Model
from crtraj.model.rate_limits import RateLimits

# the names this module has always offered (`control`: the lazily imported python-control, used by the design)
__all__ = ["TrackingCommand", "TrackingController", "TrackingRun"]


@dataclass(frozen=True)
class TrackingCommand:
    """One controller output.

    q: actuator set-point to send (nq: cable lengths mm, then z mm). x: its
    configuration. error: configuration error the law acted on (rad / mm).
    increment: set-point change in configuration (after limiting).
    rate_scale: factor (<= 1) the rate limits applied. limit_scale: extra factor
    (<= 1) that kept the set-point inside the actuation limits. accel_scale: share
    (<= 1) of the change from the previous increment that the actuator
    acceleration limits let through.
    """

    q: np.ndarray
    x: np.ndarray
    error: np.ndarray
    increment: np.ndarray
    rate_scale: float
    limit_scale: float
    accel_scale: float = 1.0

    @property
    def rate_limited(self) -> bool:
        return self.rate_scale < 1.0

    @property
    def limited(self) -> bool:
        return self.limit_scale < 1.0


@dataclass(frozen=True)
class _Period:
    """What `TrackingController.step` needs per control period h (s), computed once with the design.

    Kx, Kc: the gain's blocks on (x_ref - x) and (x_ref - x_cmd) (views of design.K); lead: design.lead;
    rate_room: largest actuator change per period (mm); vmax_room, amax_room: the rate limits' largest
    change and change of change per period (empty without rate limits).
    """

    design: TrackingDesign
    Kx: np.ndarray
    Kc: np.ndarray
    lead: np.ndarray
    rate_room: np.ndarray
    vmax_room: np.ndarray
    amax_room: np.ndarray


@dataclass(frozen=True)
class TrackingRun:
    """A closed-loop simulation (`TrackingController.simulate`).

    t (N+1,) s; x (N+1, nx) actual configurations; q (N+1, nq) actual actuator
    positions; q_command (N, nq) set-points; x_reference (N, nx); tip (N+1, 3)
    actual tip (mm); tip_reference (N+1, 3); tip_error (N+1,) mm, the distance of
    the actual tip to the reference of that period (the last entry uses the
    last reference); rate_limited, limited (N,) flags.
    """

    t: np.ndarray
    x: np.ndarray
    q: np.ndarray
    q_command: np.ndarray
    x_reference: np.ndarray
    tip: np.ndarray
    tip_reference: np.ndarray
    tip_error: np.ndarray
    rate_limited: np.ndarray
    limited: np.ndarray
    options: TrackingOptions = field(repr=False)

    @property
    def final_tip_error(self) -> float:
        return float(self.tip_error[-1])

    def summary(self) -> dict[str, Any]:
        """Tip error statistics (mm) and limiter activity."""
        e = self.tip_error
        return {
            "steps": len(self.q_command),
            "dt_s": float(self.t[1] - self.t[0]) if len(self.t) > 1 else 0.0,
            "final_tip_error_mm": float(e[-1]),
            "max_tip_error_mm": float(np.max(e)),
            "rms_tip_error_mm": float(np.sqrt(np.mean(e**2))),
            "median_tip_error_mm": float(np.median(e)),
            "p90_tip_error_mm": float(np.percentile(e, 90)),
            "rate_limited_steps": int(np.sum(self.rate_limited)),
            "limited_steps": int(np.sum(self.limited)),
        }


class TrackingController:
    """LQR-designed proportional tracking law (paper eq. 15-17) with servo model.

    Use once per control period::

        ctl = TrackingController(model, options)
        q_cmd = ctl.initial_command(x0)                 # servos settled at x0
        cmd = ctl.step(x_measured, q_cmd, x_reference)  # -> TrackingCommand
        q_cmd = cmd.q                                   # send to the actuators
    """

    def __init__(
        self, model: Model, options: TrackingOptions | None = None, *, rate_limits: RateLimits | None = None
    ) -> None:
        self.model = model
        # the actuators' speed and acceleration limits the set-points keep (the caller's share of them)
        self.rate_limits = rate_limits
        self.robot = model.robot
        self.options = TrackingOptions() if options is None else options
        o, r = self.options, self.robot
        n = r.n_segments
        self.nx, self.nq = r.nx, r.nq
        # jac_cables is constant (q is linear in x); evaluate it once.
        self._J_q = np.asarray(model.jac_cables(np.zeros(self.nx)))
        _, self._q0 = r.cable_matrix()
        self._Binv = r.cable_inverse()
        self.servo = ServoModel(r, o.servo_tau, o.servo_tau_z)
        self._tau_x = np.append(np.full(2 * n, o.servo_tau), o.servo_tau_z)
        self._rates = np.append(np.full(3 * n, o.max_cable_rate), o.max_z_rate)  # mm/s per actuator
        # Actuation limits on a set-point x: linear |A_cab x| <= stroke, z box, |C_k u| <= theta_max.
        self.limits = ActuationLimits(r, self._J_q)
        if rate_limits is not None and rate_limits.jacobian.shape[1] != self.nx:
            raise InputError(
                f"rate_limits: written for {rate_limits.jacobian.shape[1]} configuration coordinates, "
                f"robot {r.name!r} has {self.nx}"
            )
        self._tip_mode = self.options.mode == "tip"
        self._designs: dict[float, TrackingDesign] = {}
        self._periods: dict[float, _Period] = {}  # per design: the constants `step` uses
        self.design()  # fail early on a bad design
        # tip mode: one CasADi call per period gives tip(x), J(x) and tip(x_ref)
        a, b = ca.SX.sym("x", self.nx), ca.SX.sym("x_ref", self.nx)
        self._tip_jac = ca.Function("tip_jac", [a, b], [model.tip(a), model.jac_tip(a), model.tip(b)])

    # ------------------------------------------------------------------ design
    def design(self, dt: float | None = None) -> TrackingDesign:
        """The LQR design for period dt (s; default options.dt), computed once per dt."""
        dt = self.options.dt if dt is None else check_float(dt, "dt", gt=0.0)
        d = self._designs.get(dt)
        if d is None:
            if len(self._designs) >= MAX_PERIODS:
                self._designs.clear()
                self._periods.clear()
            d = lqr_design(self.options, self.robot, self._tau_x, dt)
            self._designs[dt] = d
            self._periods[dt] = self._period_constants(d)
        return d

    def _period_constants(self, d: TrackingDesign) -> _Period:
        nx, rl, h = self.nx, self.rate_limits, d.dt
        vmax_room = np.zeros(0) if rl is None else rl.vmax * h
        amax_room = np.zeros(0) if rl is None else rl.amax * h * h
        return _Period(d, d.K[:, :nx], d.K[:, nx:], d.lead, self._rates * h, vmax_room, amax_room)

    def _period(self, dt: float | None) -> _Period:
        """The per-period constants for dt (s; default options.dt). A float already designed for passed
        `design`'s check then, so the control loop skips it."""
        key = self.options.dt if dt is None else dt
        p = self._periods.get(key) if type(key) is float else None
        if p is None:
            p = self._periods[self.design(dt).dt]
        return p

    @property
    def gain(self) -> np.ndarray:
        """LQR gain K (nx, 2 nx) at options.dt: v = K (x_ref - x, x_ref - x_cmd)."""
        return self.design().K

    @property
    def proportional_gain(self) -> np.ndarray:
        """The paper's K_P = K_x + K_c (nx, nx): the gain when the servos have settled."""
        K = self.gain
        return K[:, : self.nx] + K[:, self.nx :]

    def closed_loop_eigenvalues(self, dt: float | None = None) -> np.ndarray:
        """Eigenvalues of the discrete closed-loop error dynamics A - B K."""
        return np.linalg.eigvals(self.design(dt).closed_loop)

    def step_constants(self, dt: float) -> dict[str, np.ndarray]:
        """The numbers `step` (configuration mode) and the servo model use for period dt (s), for a compiled
        copy of them (`crtraj.control.tracking._compiled`): q0 (nq) mm, Binv (nx, nq), J_q (nq, nx), Kx, Kc
        (nx, nx), lead (nx), rate_room (nq) mm, decay (nq), tau (nq) s, the rate limits' jacobian (m, nx),
        vmax_room (m), amax_room (m), amax (m) (m = 0 without), G (ng, nx) and h (ng) of the linear limits,
        C (segments, 2, nx) and tmax2 (segments,) of the bending limits, z_range (2,) mm."""
        p, rl = self._period(dt), self.rate_limits
        return {
            "q0": self._q0,
            "Binv": self._Binv,
            "J_q": self._J_q,
            "Kx": p.Kx,
            "Kc": p.Kc,
            "lead": p.lead,
            "rate_room": p.rate_room,
            "decay": self.servo.decay(p.design.dt),
            "tau": self.servo.tau,
            "jacobian": np.zeros((0, self.nx)) if rl is None else rl.jacobian,
            "vmax_room": p.vmax_room,
            "amax_room": p.amax_room,
            "amax": np.zeros(0) if rl is None else rl.amax,
            "G": self.limits.G,
            "h": self.limits.h,
            "C": np.array(self.limits.C, dtype=float),
            "tmax2": self.limits.tmax2,
            "z_range": np.array(self.limits.z_range, dtype=float),
        }

    # --------------------------------------------------------------- control
    def initial_command(self, x: np.ndarray) -> np.ndarray:
        """The set-point (nq, mm) of servos settled at configuration x."""
        return self._q0 + self._J_q @ _vec(x, self.nx, "x")

    def step(
        self,
        x_measured: np.ndarray,
        q_command: np.ndarray,
        x_reference: np.ndarray,
        dt: float | None = None,
        *,
        x_reference_rate: np.ndarray | None = None,
        tip_measured: np.ndarray | None = None,
        tip_reference: np.ndarray | None = None,
        previous_increment: np.ndarray | None = None,
    ) -> TrackingCommand:
        """One control period: the next actuator set-point.

        x_measured: actual configuration (nx). q_command: set-point the actuators
        hold now (nq, mm; from `initial_command` or the previous step).
        x_reference: planned configuration for this period (nx). dt: period (s,
        default options.dt). x_reference_rate: planned dx/dt (rad/s, mm/s): the
        paper's eq. 15 feed-forward plus a set-point lead that cancels the servo
        lag, so a ramp is tracked without steady error (None: eq. 16).
        Tip mode only (an error in configuration mode): tip_measured (3, mm;
        default: model tip of x_measured), tip_reference (3, mm; default: model
        tip of x_reference). previous_increment: the set-point's configuration change
        in the previous period (nx; default 0, at rest); used with `rate_limits` only.
        """
        p = self._period(dt)
        d = p.design
        nx = self.nx
        xm = _vec(x_measured, nx, "x_measured")
        qc = _vec(q_command, self.nq, "q_command")
        xr = _vec(x_reference, nx, "x_reference")
        xc = (qc - self._q0) @ self._Binv.T
        tip_mode = self._tip_mode
        if not tip_mode and (tip_measured is not None or tip_reference is not None):
            raise InputError("tip_measured/tip_reference: only used with tracking.mode = 'tip'")
        e = self._tip_error_config(xm, xr, tip_measured, tip_reference) if tip_mode else xr - xm
        # e_c is measured against the same (effective) reference as e.
        ec = e + xm - xc
        ff = None
        if x_reference_rate is not None:
            ff = _vec(x_reference_rate, nx, "x_reference_rate") * d.dt
            # on a ramp the servos lag their set-point by phi/(1-phi) periods' motion: lead by that
            ec = ec + p.lead * ff
        v = p.Kx @ e + p.Kc @ ec
        if ff is not None:
            v = v + ff
        v, rate_scale, accel_scale = self._rate_limited(p, v, ec, ff, previous_increment)
        v, limit_scale = self.limits.shrink(xc, v)
        q = qc + self._J_q @ v
        return TrackingCommand(q, xc + v, e, v, rate_scale, limit_scale, accel_scale)

    def _rate_limited(
        self, p: _Period, v: np.ndarray, ec: np.ndarray, ff: np.ndarray | None, v_prev: np.ndarray | None
    ) -> tuple[np.ndarray, float, float]:
        """The increment v (nx) scaled to the rate limits (direction kept) and, with the actuators' limits, to
        their speed, braking distance and acceleration (`braking`, `accelerate`): (v, rate_scale, accel_scale).
        ec: the set-point's error; ff: the reference's motion this period (None: none); v_prev: the previous
        increment (None: 0)."""
        nx = self.nx
        dq = self._J_q @ v
        over = np.abs(dq) / p.rate_room
        rl = self.rate_limits
        if rl is not None:
            over = np.concatenate([over, np.abs(rl.jacobian @ v) / p.vmax_room])
        worst = float(over.max())
        rate_scale = 1.0 / worst if worst > 1.0 else 1.0
        v = v * rate_scale
        accel_scale = 1.0
        if rl is not None:
            v = braking(rl, v, ec, np.zeros(nx) if ff is None else ff, p.design.dt, p.amax_room)
            vp = np.zeros(nx) if v_prev is None else _vec(v_prev, nx, "previous_increment")
            v, accel_scale = accelerate(rl, v, vp, p.amax_room)
        return v, rate_scale, accel_scale

    def _tip_error_config(
        self, xm: np.ndarray, xr: np.ndarray, tip_measured: np.ndarray | None, tip_reference: np.ndarray | None
    ) -> np.ndarray:
        """Configuration error from the tip error (eq. 13, 17) plus the null-space part of x_ref - x."""
        p_model, J, pr_model = self._tip_jac.call([xm, xr])
        J = np.asarray(J)
        pm = np.asarray(p_model).ravel() if tip_measured is None else _vec(tip_measured, 3, "tip_measured")
        pr = np.asarray(pr_model).ravel() if tip_reference is None else _vec(tip_reference, 3, "tip_reference")
        delta = xr - xm
        lam2 = self.options.damping**2
        # e = J+ e_p + (I - J+ J) delta with J+ = J^T (J J^T + lam^2 I)^-1
        w = np.linalg.solve(J @ J.T + lam2 * np.eye(3), (pr - pm) - J @ delta)
        return delta + J.T @ w

    # ----------------------------------------------------------- reporting
    def tip_error(
        self, x: np.ndarray, x_reference: np.ndarray | None = None, *, tip_reference: np.ndarray | None = None
    ) -> float | np.ndarray:
        """Tip tracking error(s) (mm): |tip(x) - tip_ref|; x (nx,) -> float, (N, nx) -> (N,)."""
        if (x_reference is None) == (tip_reference is None):
            raise InputError("tip_error: give exactly one of x_reference or tip_reference")
        p = self.model.tip_position(x)
        pr = self.model.tip_position(x_reference) if tip_reference is None else np.asarray(tip_reference, float)
        err = np.linalg.norm(p - pr, axis=-1)
        return float(err) if np.ndim(err) == 0 else err

    def simulate(
        self,
        x0: np.ndarray,
        reference: np.ndarray,
        steps: int | None = None,
        *,
        servo: ServoModel | None = None,
        plant: Model | None = None,
        feedforward: bool = False,
    ) -> TrackingRun:
        """Closed loop at options.dt from servos settled at x0 (nx).

        reference: (N, nx) configuration per period, or (nx,) held for `steps`
        periods. servo: actuator model of the simulated robot (default: the
        design's). plant: model of the simulated robot used for the measured and
        reported tip (default: the controller's model; a different one simulates
        model error). feedforward: pass the reference's finite-difference rate.
        """
        dt = self.options.dt
        ref = self._reference(reference, steps)
        servo = self.servo if servo is None else servo
        plant = self.model if plant is None else plant
        N = len(ref)
        # the intended tip is what the controller's model predicts for the plan
        tip_ref = self.model.tip_position(ref)
        q = self.initial_command(x0)
        qc = q.copy()
        Q = np.empty((N + 1, self.nq))
        Qc = np.empty((N, self.nq))
        X = np.empty((N + 1, self.nx))
        rl = np.zeros(N, dtype=bool)
        lim = np.zeros(N, dtype=bool)
        inc = np.zeros(self.nx)
        Q[0] = q
        tip_mode = self.options.mode == "tip"
        rate = _finite_difference_rate(ref, dt) if feedforward else None
        for k in range(N):
            x = servo.config(q)
            X[k] = x
            tm = np.asarray(plant.tip(x)).ravel() if tip_mode else None
            cmd = self.step(
                x,
                qc,
                ref[k],
                dt,
                x_reference_rate=None if rate is None else rate[k],
                tip_measured=tm,
                tip_reference=tip_ref[k] if tip_mode else None,
                previous_increment=inc,
            )
            inc = cmd.increment
            qc = cmd.q
            Qc[k], rl[k], lim[k] = qc, cmd.rate_limited, cmd.limited
            q = servo.advance(q, qc, dt)
            Q[k + 1] = q
        X[N] = servo.config(q)
        return self._run(plant, ref, tip_ref, X, (Q, Qc, rl, lim))

    def _run(
        self, plant: Model, ref: np.ndarray, tip_ref: np.ndarray, X: np.ndarray, record: tuple[np.ndarray, ...]
    ) -> TrackingRun:
        """The `TrackingRun` of a simulation: actual configurations X (N+1, nx) of `plant`, the reference (N, nx)
        and its tips (N, 3) mm, and (q, q_command, rate_limited, limited) as recorded."""
        Q, Qc, rl, lim = record
        dt, N = self.options.dt, len(ref)
        tips = plant.tip_position(X)
        tref = np.vstack([tip_ref, tip_ref[-1:]])
        err = np.linalg.norm(tips - tref, axis=1)
        t = dt * np.arange(N + 1)
        return TrackingRun(t, X, Q, Qc, np.array(ref), tips, tref, err, rl, lim, self.options)

    def _reference(self, reference: np.ndarray, steps: int | None) -> np.ndarray:
        """`simulate`'s reference as (N, nx): (N, nx) as given, or (nx,) held for `steps` periods."""
        ref = np.asarray(reference, dtype=float)
        if ref.ndim == 2 and steps is not None and steps != len(ref):
            raise InputError(f"steps: {steps} does not match the {len(ref)} reference configurations")
        if ref.ndim == 1:
            if steps is None or steps < 1:
                raise InputError("steps: must be >= 1 when reference is a single configuration")
            ref = np.broadcast_to(_vec(ref, self.nx, "reference"), (steps, self.nx))
        elif ref.ndim != 2 or ref.shape[1] != self.nx or len(ref) < 1 or not np.all(np.isfinite(ref)):
            raise InputError(f"reference: expected finite shape (N, {self.nx}), got {ref.shape}")
        return ref


def _finite_difference_rate(ref: np.ndarray, dt: float) -> np.ndarray:
    """The reference's rate (N, nx) per s by forward differences over period dt (s), 0 in the last period."""
    rate = np.zeros_like(ref)
    rate[:-1] = np.diff(ref, axis=0) / dt
    return rate


def _vec(a: Any, n: int, name: str) -> np.ndarray:
    """A finite float vector of length n (cheap check for the control loop)."""
    v = np.asarray(a, dtype=float)
    if v.shape != (n,):
        raise InputError(f"{name}: expected {n} numbers, got shape {v.shape}")
    if np.count_nonzero(np.isfinite(v)) != n:  # "all finite", at a fraction of `.all()`'s overhead
        raise InputError(f"{name}: contains NaN or infinity")
    return v
