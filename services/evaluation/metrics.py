"""Evaluation metrics for estimated joints: tangent error and its companions, the calibration
of a published covariance (docs/evaluation.md#calibration) and times to a usable model
(docs/evaluation.md#times).

Definitions follow docs/evaluation.md#tangent-error (tangent error of
Heppert et al., IROS 2022, as used by Pfisterer et al., ICRA 2025, Eq. 9), reimplemented from
that description (the reference code is GPL-3 and not used).

A joint is described by :class:`JointEstimate` ``(type, axis, point)`` in one common frame (the
camera frame for the synthetic data): ``axis`` (3,) unit direction, ``point`` (3,) a point on the
revolute axis (for prismatic joints any point, e.g. on the line through the grasp). Twists are
linear first, ``xi = [v, w]``: revolute ``[point x axis, axis]`` (unit angular speed), prismatic
``[axis, 0]``, rigid (and anything else that does not move) ``0``. All lengths in metres, angles in
radians unless a name says ``_deg``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from services.kinematics.filters.geometry import tangent_basis

Array = NDArray[np.float64]

JOINT_TYPES = ("prismatic", "revolute", "rigid")
# Below this angular speed (per unit twist magnitude) a twist counts as prismatic
# (docs/evaluation.md#tangent-error).
PRISMATIC_OMEGA_THRESHOLD = 0.01
DEFAULT_NUM_SAMPLES = 100
CONVERGENCE_THRESHOLD_DEG = 10.0


class JointLike(Protocol):
    """Anything with a joint ``type`` and ``axis``/``point`` arrays (e.g. the synthetic truth)."""

    @property
    def type(self) -> str: ...

    @property
    def axis(self) -> ArrayLike: ...

    @property
    def point(self) -> ArrayLike: ...


@dataclass(frozen=True, eq=False)
class JointEstimate:
    """A 1-DOF joint (or a rigid connection) in a common frame.

    ``type``: "prismatic", "revolute" or "rigid". ``axis`` (3,): unit direction (normalised here;
    ignored for rigid). ``point`` (3,) [m]: a point on the axis (revolute) or on the sliding line
    (prismatic; irrelevant to the direction of motion).
    """

    type: str
    axis: Array
    point: Array

    def __post_init__(self) -> None:
        if self.type not in JOINT_TYPES:
            raise ValueError(f"joint type must be one of {JOINT_TYPES}, got {self.type!r}")
        axis = np.asarray(self.axis, dtype=float).reshape(-1)
        point = np.asarray(self.point, dtype=float).reshape(-1)
        if axis.shape != (3,) or point.shape != (3,):
            raise ValueError(f"axis and point must have 3 elements, got {axis.shape}, {point.shape}")
        if not (np.all(np.isfinite(axis)) and np.all(np.isfinite(point))):
            raise ValueError("axis and point must be finite")
        n = float(np.linalg.norm(axis))
        if self.type != "rigid":
            if n < 1e-12:
                raise ValueError("a prismatic or revolute joint needs a non-zero axis")
            axis = axis / n
        object.__setattr__(self, "axis", axis)
        object.__setattr__(self, "point", point)

    @classmethod
    def rigid(cls) -> JointEstimate:
        """A rigid connection (no motion)."""
        return cls("rigid", np.zeros(3), np.zeros(3))

    @classmethod
    def from_joint(cls, joint: JointLike) -> JointEstimate:
        """Copy any :class:`JointLike` (e.g. ``services.synthetic.generator.JointTruth``)."""
        return cls(str(joint.type), np.asarray(joint.axis, dtype=float),
                   np.asarray(joint.point, dtype=float))

    @classmethod
    def from_twist(cls, xi: ArrayLike, point_hint: ArrayLike | None = None,
                   eps: float = 1e-9) -> JointEstimate:
        """Joint of a twist ``[v, w]`` (6,); the screw pitch, if any, is dropped.

        ``|w| < 0.01 |xi|`` -> prismatic along ``v`` (point: ``point_hint`` or the origin);
        ``|xi| < eps`` -> rigid; otherwise revolute about ``w`` through ``w x v / |w|^2``.
        """
        x = np.asarray(xi, dtype=float).reshape(6)
        v, w = x[:3], x[3:]
        norm = float(np.linalg.norm(x))
        if norm < eps:
            return cls.rigid()
        wn = float(np.linalg.norm(w))
        if wn < PRISMATIC_OMEGA_THRESHOLD * norm:
            hint = np.zeros(3) if point_hint is None else np.asarray(point_hint, dtype=float)
            return cls("prismatic", v, hint)
        return cls("revolute", w, np.cross(w, v) / (wn * wn))

    def to_twist(self) -> Array:
        """Unit twist ``[v, w]`` (6,): revolute ``[p x a, a]``, prismatic ``[a, 0]``, rigid 0."""
        return joint_twist(self)


def _as_joint(j: JointLike) -> JointEstimate:
    return j if isinstance(j, JointEstimate) else JointEstimate.from_joint(j)


def joint_twist(joint: JointLike) -> Array:
    """Unit twist (6,) of a joint (see :meth:`JointEstimate.to_twist`)."""
    j = _as_joint(joint)
    if j.type == "rigid":
        return np.zeros(6)
    if j.type == "prismatic":
        return np.concatenate([j.axis, np.zeros(3)])
    return np.concatenate([np.cross(j.point, j.axis), j.axis])


def closest_point_to_origin(axis: ArrayLike, point: ArrayLike) -> Array:
    """Point (3,) of the line ``point + s * axis`` closest to the origin."""
    a = np.asarray(axis, dtype=float)
    a = a / np.linalg.norm(a)
    p = np.asarray(point, dtype=float)
    return p - (p @ a) * a


def _is_prismatic_twist(xi: Array) -> bool:
    return float(np.linalg.norm(xi[3:])) < PRISMATIC_OMEGA_THRESHOLD * float(np.linalg.norm(xi))


def _tangents(xi: Array, x: Array) -> Array:
    """Unnormalised tangents ``v + w x x`` (M, 3) of twist ``xi`` at points ``x`` (M, 3)."""
    return xi[:3] + np.cross(xi[3:], x)


def gt_path_samples(xi_gt: ArrayLike, positions: ArrayLike,
                    num_samples: int = DEFAULT_NUM_SAMPLES) -> Array:
    """Points (num_samples, 3) on the GT path covering the demonstrated range (tangent error steps 1-2).

    ``positions`` (K, 3): observed demonstration positions (grasp/part/hand points; non-finite
    rows are dropped). Prismatic GT (``|w| < 0.01 |xi|``): ``n = v/|v|``, ``z_k = x_k . n``,
    ``q_max = max z - min z``, ``x0 = (min z) n + mean(x_k - z_k n)``, samples ``x0 + q n``.
    Revolute GT: axis point ``c = w x v / |w|^2``; radial parts ``r_k`` of ``x_k - c``; mean radius
    ``r``; angles of ``r_k`` in a basis with z along ``w``; the largest circular gap between sorted
    angles ends at ``q_min`` and starts after ``q_max``; span ``(q_max - q_min) mod 2 pi``;
    ``x0`` = the ``q_min`` observation with its radial part rescaled to ``r``; samples
    ``exp(q xi_hat) x0`` with ``xi_hat = xi / |w|``; ``q`` uniform in [0, span].
    """
    xi = np.asarray(xi_gt, dtype=float).reshape(6)
    x = np.asarray(positions, dtype=float).reshape(-1, 3)
    x = x[np.all(np.isfinite(x), axis=1)]
    if len(x) == 0:
        raise ValueError("no finite demonstration positions")
    if float(np.linalg.norm(xi)) == 0.0:
        raise ValueError("the ground-truth twist is zero")
    qs = np.linspace(0.0, 1.0, num_samples)
    if _is_prismatic_twist(xi):
        n = xi[:3] / np.linalg.norm(xi[:3])
        z = x @ n
        q_max = float(z.max() - z.min())
        x0 = float(z.min()) * n + (x - z[:, None] * n).mean(axis=0)
        return x0 + (qs * q_max)[:, None] * n
    w = xi[3:]
    wn = float(np.linalg.norm(w))
    xi_hat = xi / wn
    a = w / wn
    c = np.cross(w, xi[:3]) / (wn * wn)
    d = x - c
    axial = d @ a
    radial = d - axial[:, None] * a
    r = float(np.linalg.norm(radial, axis=1).mean())
    # Basis (e1, e2, a), right-handed, so angles grow with positive rotation about w.
    helper = np.array([1.0, 0.0, 0.0]) if abs(a[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(a, helper)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(a, e1)
    theta = np.mod(np.arctan2(radial @ e2, radial @ e1), 2.0 * math.pi)
    order = np.argsort(theta)
    ts = theta[order]
    gaps = np.diff(np.concatenate([ts, [ts[0] + 2.0 * math.pi]]))
    g = int(np.argmax(gaps))
    i_min = int(order[(g + 1) % len(ts)])
    i_max = int(order[g])
    span = float(np.mod(theta[i_max] - theta[i_min], 2.0 * math.pi))
    rk = radial[i_min]
    rn = float(np.linalg.norm(rk))
    x0 = c + axial[i_min] * a + (rk * (r / rn) if rn > 0.0 else rk)
    # exp(q xi_hat) x0 = c + R(q) (x0 - c) + pitch q a (Rodrigues; pitch = a . v_hat).
    q = qs * span
    pitch = float(a @ xi_hat[:3])
    d0 = x0 - c
    along = (d0 @ a) * a
    perp = d0 - along
    rot = (np.outer(np.cos(q), perp) + np.outer(np.sin(q), np.cross(a, perp)) + along)
    return c + rot + np.outer(pitch * q, a)


def tangent_cosines(xi_gt: ArrayLike, xi_est: ArrayLike, positions: ArrayLike,
                    num_samples: int = DEFAULT_NUM_SAMPLES) -> Array:
    """Raw cosines ``s_i = u_gt . u_est`` (num_samples,) at the GT path samples, before any flip.

    ``u(x) = normalize(v + w x x)``; where the estimated (or GT) tangent vanishes (the sample lies
    on that axis) ``s_i = 0``. A zero estimated twist gives all zeros.
    """
    xe = np.asarray(xi_est, dtype=float).reshape(6)
    xg = np.asarray(xi_gt, dtype=float).reshape(6)
    xs = gt_path_samples(xg, positions, num_samples)
    s = np.zeros(len(xs))
    if float(np.linalg.norm(xe)) == 0.0:
        return s
    tg = _tangents(xg, xs)
    te = _tangents(xe, xs)
    ng = np.linalg.norm(tg, axis=1)
    ne = np.linalg.norm(te, axis=1)
    ok = (ng > float(np.linalg.norm(xg)) * 1e-12) & (ne > float(np.linalg.norm(xe)) * 1e-12)
    s[ok] = np.einsum("ij,ij->i", tg[ok], te[ok]) / (ng[ok] * ne[ok])
    return s


def tangent_error_from_cosines(s: Array) -> tuple[float, float]:
    """(error [rad], similarity) from raw cosines (M,): global flip if >= half are negative."""
    if np.count_nonzero(s < 0.0) >= 0.5 * len(s):
        s = -s
    s = np.clip(s, -1.0, 1.0)
    return float(np.mean(np.arccos(s))), float(np.clip(np.mean(s), -1.0, 1.0))


def tangent_error_from_twists(xi_gt: ArrayLike, xi_est: ArrayLike, positions: ArrayLike,
                              num_samples: int = DEFAULT_NUM_SAMPLES) -> tuple[float, float]:
    """Tangent error [rad] and similarity of twist ``xi_est`` against ``xi_gt`` (docs/evaluation.md).

    Both twists (6,) are linear first and in the frame of ``positions`` (K, 3). With the raw
    cosines ``s_i`` of :func:`tangent_cosines`: if at least half of them are negative, all flip
    sign (the axis sign is ambiguous); error = mean arccos(clip(s_i)), similarity = clip(mean
    s_i, -1, 1). A zero (rigid) estimate gives (pi/2, 0).

    Invariant to the scale of either twist, and to the sign of either twist except at an exact
    tie (exactly half of the cosines negative), where the rule "at least half" flips one sign
    and not the other. The error lies in [0, pi): it exceeds pi/2 only when fewer than half of
    the tangents are opposed but those are opposed strongly.
    """
    xe = np.asarray(xi_est, dtype=float).reshape(6)
    if float(np.linalg.norm(xe)) == 0.0:
        return math.pi / 2.0, 0.0
    return tangent_error_from_cosines(tangent_cosines(xi_gt, xe, positions, num_samples))


def tangent_error(gt: JointLike, est: JointLike | None, positions: ArrayLike,
                  num_samples: int = DEFAULT_NUM_SAMPLES) -> float:
    """Tangent error [rad] of joint ``est`` against ``gt`` over the demonstrated range.

    ``est = None`` (no estimate yet) and rigid estimates give pi/2. See
    :func:`tangent_error_from_twists`.
    """
    if est is None:
        return math.pi / 2.0
    return tangent_error_from_twists(joint_twist(gt), joint_twist(est), positions,
                                     num_samples)[0]


def tangent_similarity(gt: JointLike, est: JointLike | None, positions: ArrayLike,
                       num_samples: int = DEFAULT_NUM_SAMPLES) -> float:
    """Tangent similarity in [-1, 1] (clipped mean of the sign-aligned cosines); 0 for none."""
    if est is None:
        return 0.0
    return tangent_error_from_twists(joint_twist(gt), joint_twist(est), positions,
                                     num_samples)[1]


def axis_angle_error(gt: JointLike, est: JointLike) -> float:
    """Angle [rad] between the two axis directions, folded to [0, pi/2] (sign-free).

    Rigid joints have no axis: the error is pi/2 if either is rigid.
    """
    g, e = _as_joint(gt), _as_joint(est)
    if g.type == "rigid" or e.type == "rigid":
        return math.pi / 2.0
    c = abs(float(np.clip(g.axis @ e.axis, -1.0, 1.0)))
    return float(math.acos(min(c, 1.0)))


def axis_line_distance(gt: JointLike, est: JointLike) -> float:
    """Distance [m] between the two axis lines (Pluecker form, ScrewNet, Jain et al. 2021).

    Lines ``(l, m = p x l)`` with unit ``l``: parallel lines give ``|l x (m1 - m2)|`` (after
    aligning the signs), skew lines ``|l1 . m2 + l2 . m1| / |l1 x l2|``. Defined for two revolute
    joints; NaN otherwise (a prismatic joint has no axis location).
    """
    g, e = _as_joint(gt), _as_joint(est)
    if g.type != "revolute" or e.type != "revolute":
        return float("nan")
    l1, l2 = g.axis, e.axis
    if l1 @ l2 < 0.0:
        l2 = -l2
    m1, m2 = np.cross(g.point, l1), np.cross(e.point, l2)
    cross = np.cross(l1, l2)
    cn = float(np.linalg.norm(cross))
    if cn < 1e-9:
        return float(np.linalg.norm(np.cross(l1, m1 - m2)))
    return float(abs(l1 @ m2 + l2 @ m1) / cn)


def type_accuracy(gt_types: Sequence[str], est_types: Sequence[str | None]) -> float:
    """Fraction of estimates whose joint type equals the ground truth (``None`` counts wrong)."""
    if len(gt_types) != len(est_types):
        raise ValueError("gt_types and est_types differ in length")
    if not gt_types:
        raise ValueError("no joints to compare")
    return sum(g == e for g, e in zip(gt_types, est_types, strict=True)) / len(gt_types)


def tangent_errors_over_time(gt: JointLike, estimates: Sequence[JointLike | None],
                             positions: ArrayLike,
                             num_samples: int = DEFAULT_NUM_SAMPLES) -> Array:
    """Tangent error [rad] (M,) of each estimate in a time series (None or rigid -> pi/2)."""
    xg = joint_twist(gt)
    pos = np.asarray(positions, dtype=float)
    out = np.full(len(estimates), math.pi / 2.0)
    for i, est in enumerate(estimates):
        if est is not None:
            out[i] = tangent_error_from_twists(xg, joint_twist(est), pos, num_samples)[0]
    return out


def time_to_converge(stamps_ns: ArrayLike, errors_rad: ArrayLike,
                     threshold_deg: float = CONVERGENCE_THRESHOLD_DEG,
                     start_ns: int | None = None) -> float | None:
    """Seconds from ``start_ns`` (default: the first stamp) until the error stays below
    ``threshold_deg`` for good.

    ``stamps_ns`` (M,) increasing int stamps, ``errors_rad`` (M,) the tangent error of the
    estimate available at each stamp (e.g. :func:`tangent_errors_over_time`). Returns the time of
    the first sample from which every later error is below the threshold, or ``None`` if the last
    one is not (:func:`time_held_from`).
    """
    st = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
    err = np.asarray(errors_rad, dtype=float).reshape(-1)
    if st.shape != err.shape or len(st) == 0:
        raise ValueError("stamps and errors must be non-empty and of equal length")
    return time_held_from(st, err < math.radians(threshold_deg), start_ns)


def time_to_converge_estimates(stamps_ns: ArrayLike, estimates: Sequence[JointLike | None],
                               gt: JointLike, positions: ArrayLike,
                               threshold_deg: float = CONVERGENCE_THRESHOLD_DEG) -> float | None:
    """:func:`time_to_converge` of a time series of estimates (None = no estimate yet)."""
    return time_to_converge(stamps_ns, tangent_errors_over_time(gt, estimates, positions),
                            threshold_deg)


# --------------------------------------------------------------------------------------------
# Calibration of the published covariance (docs/evaluation.md#calibration)
# --------------------------------------------------------------------------------------------

# 90 % quantile of the chi-square distribution with 2 degrees of freedom: its CDF is
# 1 - exp(-x / 2), so the quantile is -2 ln(1 - 0.9), exactly.
CHI2_2DOF_90 = -2.0 * math.log(0.1)
INTERVAL_LEVEL = 0.9


def _mahalanobis2(r: Array, cov: Array) -> float:
    """``r' cov^-1 r`` for a 2-vector; inf when ``cov`` is not finite and positive definite
    (a covariance that claims certainty, or none, covers nothing)."""
    c = np.asarray(cov, dtype=float)
    if c.shape != (2, 2) or not np.all(np.isfinite(c)):
        return math.inf
    c = 0.5 * (c + c.T)
    try:
        chol = np.linalg.cholesky(c)
    except np.linalg.LinAlgError:
        return math.inf
    y = np.linalg.solve(chol, r)
    return float(y @ y)


def axis_direction_d2(true_axis: ArrayLike, est_axis: ArrayLike, cov_b: ArrayLike) -> float:
    """Squared Mahalanobis distance of the true axis direction from the estimated one.

    ``est_axis`` (3,) unit estimated direction ``u``, ``cov_b`` (2, 2) [rad^2] the published
    covariance of its tangent coordinates ``(b1, b2)`` in ``tangent_basis(u)`` (``B``, 3x2;
    docs/protocol.md), ``true_axis`` (3,) the true direction, sign-folded to ``a . u >= 0``
    (a line's direction has no sign). The tangent coordinates that turn ``u`` into ``a``
    exactly, ``Exp(u x (B b)) u = a``, are ``b = theta B'a / |B'a|`` with ``theta`` the angle
    between them; returns ``b' cov_b^-1 b``, chi-square with 2 dof when the covariance is right.
    """
    u = np.asarray(est_axis, dtype=float).reshape(3)
    u = u / np.linalg.norm(u)
    a = np.asarray(true_axis, dtype=float).reshape(3)
    a = a / np.linalg.norm(a)
    if a @ u < 0.0:
        a = -a
    s = tangent_basis(u).T @ a
    sn = float(np.linalg.norm(s))
    theta = math.atan2(sn, float(a @ u))
    b = s * (theta / sn) if sn > 0.0 else np.zeros(2)
    return _mahalanobis2(b, np.asarray(cov_b, dtype=float))


def axis_position_d2(true_axis: ArrayLike, true_point: ArrayLike, est_axis: ArrayLike,
                     est_point: ArrayLike, cov_point: ArrayLike) -> float:
    """Squared Mahalanobis distance of the true revolute axis from the estimated axis point.

    ``est_point`` (3,) [m] the published point ``p`` of the estimated axis ``u`` (3,), with its
    published covariance ``cov_point`` (3, 3) [m^2]; ``true_axis``/``true_point`` any point and
    the direction of the true axis line. The true line meets the plane through ``p`` normal to
    ``u`` at ``x``; the residual ``r = B'(x - p)`` (2,) in ``tangent_basis(u)`` is compared
    with the covariance projected on that plane, ``B' cov_point B``: returns
    ``r' (B' cov_point B)^-1 r``, chi-square with 2 dof when the covariance is right. A true
    axis (nearly) parallel to the plane never meets it: inf.
    """
    u = np.asarray(est_axis, dtype=float).reshape(3)
    u = u / np.linalg.norm(u)
    a = np.asarray(true_axis, dtype=float).reshape(3)
    a = a / np.linalg.norm(a)
    p = np.asarray(est_point, dtype=float).reshape(3)
    q = np.asarray(true_point, dtype=float).reshape(3)
    along = float(a @ u)
    if abs(along) < 1e-9:
        return math.inf
    x = q + (float((p - q) @ u) / along) * a
    B = tangent_basis(u)
    cov = np.asarray(cov_point, dtype=float).reshape(3, 3)
    return _mahalanobis2(B.T @ (x - p), B.T @ cov @ B)


def coverage(d2: Sequence[float], quantile: float = CHI2_2DOF_90) -> tuple[int, int]:
    """(covered, defined): how many of the squared distances ``d2`` lie inside the interval
    (``d2 <= quantile``) and how many are defined (NaN = no interval to check; inf counts as
    defined and outside)."""
    values = [float(v) for v in d2 if not math.isnan(float(v))]
    return sum(v <= quantile for v in values), len(values)


# --------------------------------------------------------------------------------------------
# Times to a usable model (docs/evaluation.md#times)
# --------------------------------------------------------------------------------------------


def time_held_from(stamps_ns: ArrayLike, ok: ArrayLike, start_ns: int | None = None
                   ) -> float | None:
    """Seconds from ``start_ns`` (default: the first stamp) until ``ok`` holds for good.

    ``stamps_ns`` (M,) increasing int stamps, ``ok`` (M,) bool per stamp. Returns the time of
    the first stamp from which every later ``ok`` is true (0 if that is before ``start_ns``),
    or ``None`` if the last one is false ("never").
    """
    st = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
    good = np.asarray(ok, dtype=bool).reshape(-1)
    if st.shape != good.shape or len(st) == 0:
        raise ValueError("stamps and flags must be non-empty and of equal length")
    if not good[-1]:
        return None
    bad = np.flatnonzero(~good)
    first = 0 if len(bad) == 0 else int(bad[-1]) + 1
    start = int(st[0]) if start_ns is None else int(start_ns)
    return float(max(0, int(st[first]) - start)) * 1e-9


@dataclass(frozen=True)
class TimeSummary:
    """Times [s] over demonstrations: median and 90th percentile of those that got there
    (NaN if none did), how many did, and how many never did."""

    median_s: float
    p90_s: float
    reached: int
    never: int


def summarise_times(times: Sequence[float | None]) -> TimeSummary:
    """:class:`TimeSummary` of per-demonstration times (None or NaN = never)."""
    got = [float(t) for t in times if t is not None and not math.isnan(float(t))]
    never = len(times) - len(got)
    if not got:
        return TimeSummary(math.nan, math.nan, 0, never)
    return TimeSummary(float(np.median(got)), float(np.percentile(got, 90)), len(got), never)
