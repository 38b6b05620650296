"""The Cosserat rod driven by a PCC robot's actuation, in the robot's actuation mode: configuration -> shape.

How the actuators drive the tendons is part of the model (``[robot.mechanics] actuation``), because the rod
takes a different shape under each for the same commanded configuration:

- "cable_length" (the default): crtraj's servos are position controlled; each sets how much tendon lies
  between the base disc and the tendon's end disc. `RodDrive` turns the actuation q (mm,
  `crtraj.model.robot.Robot.cables`) into those commanded lengths and solves the rod in cable-length mode
  (`crtraj.model.cosserat._cables`): the rod finds its own tensions, so its weight is partly carried by them.
- "tension": force-controlled actuators hold the tensions that keep the PCC bending on a weightless rod
  (`crtraj.model.cosserat.tensions_for_bending`), and the rod is solved under those fixed tensions
  (`crtraj.model.cosserat.CosseratRod`): the weight bends it further, nothing pulls it back.

Every consumer of the rod (the plant, `crtraj verify --model cosserat`, `crtraj model compare`) builds its rod
here, so they all see the robot file's mode. The cable-length map:

The length map. The configuration x = `Robot.config(q)` has effective bending vectors u_bar_k (rad,
`Robot.bending`). On a circular arc a tendon at the body-frame angle a, radius r, has the path
``L - r u_bar . (cos a, sin a)`` exactly, and a tendon of segment k passes every segment j <= k. The
tensions that hold that shape on a weightless rod are `crtraj.model.cosserat.tensions_for_bending`
(the smallest of each segment equal to `pretension`); under them the backbone shortens by
``F_j / EA`` per length (F_j: the tensions passing segment j) and each tendon stretches by
``1 + tau_i / EA_t``. The commanded (unstretched) length is the path so shortened, divided by that
stretch:

    l_i = sum_{j <= k} (L_j (1 - F_j / EA) - r u_bar_j . (cos a_i, sin a_i)) / (1 + tau_i / EA_t)

This is the drive of a robot whose servos were zeroed on the straight pose under pretension and that
compensates the tendons' stretch with PCC's own tensions: the rod then differs from PCC only by
mechanics the PCC model leaves out (how the tendon loads act along the rod, gravity, any tip load).
Without the stretch compensation the rod would miss PCC by tens of mm: holding cdsr2's segment at
pi takes about 40 N, which stretches a 9000 N tendon 0.9 mm over 200 mm, 0.35 rad at r = 2.5 mm.

The rod's backbone is in its base frame with the base at the origin; the robot's base stage moves it by
the actuation's last entry z (mm) along the base axis. Units: mm, N, rad.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from crtraj.core.errors import InputError
from crtraj.core.fields import check_array, check_float
from crtraj.model.cosserat._cables import CableDrivenRod
from crtraj.model.cosserat._map import tensions_for_bending
from crtraj.model.cosserat._statics import NO_LOAD, POLISH, CosseratRod, RodLoad, RodSolution
from crtraj.model.mechanics import Mechanics
from crtraj.model.robot import Robot

log = logging.getLogger(__name__)

# Largest pretension (N): a few times the tension that bends a segment of cdsr2 through pi (about 40 N).
MAX_PRETENSION = 200.0


@dataclass(frozen=True)
class RodShape:
    """One solve of the driven rod. points: backbone (mm, world frame: base stage applied), NaN rows when
    the solve failed; rod: the statics solution (status, base wrench); tensions: the tendons' tensions (N,
    cable order; in cable-length mode those the rod took, NaN when the solve failed); slack: the tendons that
    went slack (cable-length mode; never in tension mode)."""

    points: np.ndarray
    rod: RodSolution
    tensions: np.ndarray
    slack: np.ndarray

    def is_success(self) -> bool:
        return self.rod.is_success()

    @property
    def tip(self) -> np.ndarray:
        """Tip position (mm, world frame)."""
        return self.points[-1]

    @property
    def status(self) -> str:
        return self.rod.status


class RodDrive:
    """The rod of `robot` driven by actuation q in the robot's actuation mode (see the module docstring).

    mech: the ``[robot.mechanics]`` (default: the robot file's; `InputError` when it has none); its
    ``actuation`` picks the mode. pretension: N in every tendon at the straight pose (both modes: the
    smallest tension of each segment). gravity: apply the robot's weight (`Mechanics.weight_per_length`);
    False: a weightless rod (no load). polish: the tension-mode solves' polish (`CosseratRod.solve_path`; 1
    stops each compiled solve as soon as it is within the tolerance).
    """

    def __init__(
        self,
        robot: Robot,
        mech: Mechanics | None = None,
        *,
        pretension: float = 1.0,
        gravity: bool = True,
        polish: float = POLISH,
    ) -> None:
        self.robot = robot
        self.mech = Mechanics.from_robot(robot) if mech is None else mech
        self.pretension = check_float(pretension, "pretension", gt=0.0, le=MAX_PRETENSION)
        self.gravity = bool(gravity)
        self.load = RodLoad() if self.gravity else NO_LOAD
        self.polish = float(polish)
        self.rod: CableDrivenRod | CosseratRod
        if self.actuation == "tension":
            self.rod = CosseratRod(robot, self.mech)
        else:
            self.rod = CableDrivenRod(robot, self.mech)

    @property
    def actuation(self) -> str:
        """The actuation mode: "cable_length" or "tension" (``[robot.mechanics] actuation``)."""
        return self.mech.actuation

    def describe(self) -> str:
        """A few words on the model, for printed output: mode and gravity."""
        return f"actuation {self.actuation}, {'with gravity' if self.gravity else 'weightless'}"

    def tensions(self, q: np.ndarray) -> np.ndarray:
        """The tensions (N, cable order) that hold the PCC bending of actuation q (mm) on a weightless rod,
        the smallest of each segment equal to the pretension: what tension mode holds fixed."""
        r = self.robot
        q = check_array(np.asarray(q, dtype=float), "q", (r.nq,))
        ub = r.bending(r.config(q)).reshape(r.n_segments, 2)
        return tensions_for_bending(r, self.mech, ub, self.pretension)

    def lengths(self, q: np.ndarray) -> np.ndarray:
        """Commanded tendon lengths (mm, cable order) for actuation q (nq,) mm (the module docstring)."""
        r, m = self.robot, self.mech
        q = check_array(np.asarray(q, dtype=float), "q", (r.nq,))
        n = r.n_segments
        ub = r.bending(r.config(q)).reshape(n, 2)
        tau = tensions_for_bending(r, m, ub, self.pretension)
        passing = np.cumsum(tau.reshape(n, 3).sum(axis=1)[::-1])[::-1]  # N through each segment
        lengths = np.array([s.length for s in r.segments])
        short = lengths * (1.0 - passing / (m.youngs_modulus * m.area))
        if np.any(short <= 0.0):  # the robot file's mechanics, not this pose: name them
            raise InputError(
                f"robot.mechanics.youngs_modulus: {m.youngs_modulus:g} MPa is too soft for the tendons' tension "
                f"({float(passing.max()):.3g} N would shorten a segment to {float(short.min()):.3g} mm); check "
                "youngs_modulus and the wire's diameter"
            )
        out = np.empty(3 * n)
        for k in range(n):
            d = np.stack([np.cos(r.cable_angles(k)), np.sin(r.cable_angles(k))], axis=1)  # (3, 2)
            path = short[: k + 1].sum() - r.cable_radius * d @ ub[: k + 1].sum(axis=0)
            out[3 * k : 3 * k + 3] = path / (1.0 + tau[3 * k : 3 * k + 3] / m.tendon_stiffness)
        return out

    def shape(self, q: np.ndarray) -> RodShape:
        """The rod's shape at actuation q (mm) in the robot's actuation mode, warm-started from the last
        solve; the points are NaN when the solve did not converge (its status says why)."""
        if self.actuation == "tension":
            tau = self.tensions(q)
            assert isinstance(self.rod, CosseratRod)
            sol = self.rod.solve_path(tau[None, :], self.load, polish=self.polish)[0]
            shape = RodShape(np.array(sol.points, dtype=float), sol, tau, np.zeros(tau.size, dtype=bool))
        else:
            ell = self.lengths(q)
            if np.any(ell <= 0.0):
                raise InputError(f"q: gives a tendon length <= 0 mm ({float(ell.min()):.3g} mm)")
            assert isinstance(self.rod, CableDrivenRod)
            cab = self.rod.solve(ell, self.load)
            shape = RodShape(np.array(cab.rod.points, dtype=float), cab.rod, cab.tensions, cab.slack)
        shape.points[:, 2] += float(q[-1])  # the base stage
        return shape

    def shape_config(self, x: np.ndarray) -> RodShape:
        """The rod's shape at configuration x (nx,) (the PCC parameters and the base translation, mm)."""
        return self.shape(self.robot.cables(np.asarray(x, dtype=float)))

    def nodes(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Backbone nodes (N, n_segments steps + 1, 3) mm, world frame, of configurations x (N, nx) solved in
        turn (each warm-started from the last: a path or a batch of nearby configurations), NaN rows where a
        solve failed; and the failed mask (N,)."""
        x = np.atleast_2d(np.asarray(x, dtype=float))
        out = np.full((len(x), self.robot.n_segments * self.mech.steps + 1, 3), np.nan)
        failed = np.zeros(len(x), dtype=bool)
        if self.actuation == "tension":  # every frame's tensions at once, checked once (verify's long paths)
            assert isinstance(self.rod, CosseratRod)
            tau = tensions_for_bending(self.robot, self.mech, self.robot.bending(x), self.pretension)
            sols = self.rod.solve_path(tau, self.load, polish=self.polish)
            shapes = [sol.points + np.array([0.0, 0.0, xi[-1]]) for sol, xi in zip(sols, x, strict=True)]
        else:
            shapes = [self.shape_config(xi).points for xi in x]
        for i, pts in enumerate(shapes):
            if np.all(np.isfinite(pts)):
                out[i] = pts
            else:
                failed[i] = True
        return out, failed

    def point_at(self, points: np.ndarray, segment: int, arc: float | None) -> np.ndarray:
        """The backbone point (3,) mm at `arc` mm along `segment` (0-based; None: its end) of `points`
        (a `shape`'s), interpolated linearly between the rod's integration nodes (exact at nodes)."""
        seg = self.robot.segments[segment]
        steps = self.mech.steps
        f = steps if arc is None else float(arc) / seg.length * steps
        i = min(int(np.floor(f)), steps - 1)
        w = f - i
        base = segment * steps
        return (1.0 - w) * points[base + i] + w * points[base + i + 1]
