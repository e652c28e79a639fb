"""Model selection over the joint hypotheses (OMIP's structure, in log space).

Structure (docs/estimation.md#model-selection, which also lists the departures from OMIP):

- History: one sample per frame, the hand displacement ``d_k = c(k) - c(t0)`` [m] (``c`` = hand origin
  in ``frame``) and the rotation ``R_k`` of the delta ``D_k = T(k) T(t0)^-1``, with the prismatic and
  revolute joint values estimated at that frame (stored after the frame's correction, so without
  OMIP's one-frame lag), and the rigid test of the frame (below). Bounded memory: when
  ``history_capacity`` samples are stored, every other one is dropped and only every ``stride``-th
  later frame is stored (``stride`` doubles), so the samples stay uniformly spaced over the whole
  demonstration.
- ``m = min(n, N)`` samples are drawn at ``k_j = round(j max(1, n / N))``, ``j = 0..m-1``.
- Per sample and joint hypothesis: ``e_t = |d_j - d_hyp|`` [m], the distance between the measured
  hand position and the one the hypothesis predicts (including the filter's reference correction),
  and ``e_r = angle(R_j^T R_hyp)`` [rad]. OMIP compares the translations of the deltas instead, i.e.
  the motion of the frame origin, which scales every rotation error by the distance from the camera
  to the object; the hand point makes ``e_t`` independent of the frame;
  ``log N_j = log N1(e_t; 0, sigma_t) + log N1(e_r; 0, sigma_r)`` (normalised 1-D normal densities,
  at most ``log 15.92``). The hypotheses' errors are defined by each filter's ``history_errors``;
  :meth:`ModelSelector.log_scores` evaluates the same quantities in a fused, vectorised form.
- Rigid test (docs/estimation.md#rigid-test): rigid's errors are by how many sigmas the displacement
  and the rotation of the delta exceed ``rigid_test_sigmas`` of their published covariance
  (``x = max(0, sqrt(d2) - k)``, standardised: they enter as ``e = x sigma``); the prismatic
  hypothesis' rotation error is rigid's (the same prediction, no rotation).
- ``log L`` aggregates the samples: ``"tempered"`` (default) sums ``log((1 - eps) N_j + eps c)``
  (``c`` = ``disconnected_density``, ``eps`` = ``likelihood_outlier_weight``) and scales the sum by
  ``n_eff / m``, ``n_eff = clip(duration / likelihood_correlation_time_s, 1, m)``; ``"product"``
  sums the ``log N_j``; ``"mean"`` is OMIP's arithmetic mean, ``logsumexp(log N_j) - log m``.
- Unnormalised log scores: rigid and prismatic ``log prior + log L``; revolute
  ``log prior + log L + log N1(d; 0, revolute_max_joint_distance_m)``, ``d`` the distance from the
  axis to the current hand origin; disconnected ``log prior + k log(disconnected_density)`` with
  ``k = n_eff`` for "tempered", ``m`` for "product" and ``1`` for "mean" (OMIP's constant 0.8). A
  joint filter that has not started (too little motion) scores 0 (log -inf).
- Posterior = softmax of the log scores over ``JOINT_TYPES``; ties go to the earlier type.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from services.common.snapshot import SnapshotError, SnapshotReader
from services.kinematics.config import KinematicsConfig
from services.kinematics.filters import JOINT_TYPES, PrismaticJoint, RevoluteJoint

Array = NDArray[np.float64]

_LOG_2PI = math.log(2.0 * math.pi)

# Per-sample features (columns of DeltaHistory.data). Every hypothesis' squared translation error
# and the cosine of its rotation error are linear in them, so a hypothesis is scored by one matrix
# product with a coefficient vector (and, summed over the samples, by one dot product).
_ONE = 0  # 1
_D = slice(1, 4)  # hand displacement d (3) [m]
_DD = 4  # |d|^2
_ANG2 = 5  # squared rotation angle of the delta [rad^2]
_QP = 6  # prismatic joint value qp [m]
_QP2 = 7  # qp^2
_QPD = slice(8, 11)  # qp d
_SIN = 11  # s = sin(qr), qr the revolute joint value
_VERS = 12  # v = 1 - cos(qr)
_SD = slice(13, 16)  # s d
_VD = slice(16, 19)  # v d
_R = slice(19, 28)  # delta rotation, row-major (9)
_SR = slice(28, 37)  # s R
_VR = slice(37, 46)  # v R
_RT2 = 46  # rigid test: displacement beyond the test, squared [sigmas^2]
_RR2 = 47  # rigid test: rotation beyond the test, squared [sigmas^2] (rigid and prismatic)
_NFEAT = 48
_NFEAT_T = 19  # features that enter the translation errors of the joints
_QR = 48  # revolute joint value qr [rad] (not a feature)
_FRAME = 49  # frame index since t0 (not a feature)
_NCOL = 50


class DeltaHistory:
    """Bounded, uniformly spaced store of per-frame samples (see the module docstring).

    ``data`` (capacity x 50, the first ``n`` rows valid) holds per sample the features
    ``[1, d, |d|^2, angle^2, qp, qp^2, qp d, s, v, s d, v d, R, s R, v R, et^2, er^2]`` (``d`` hand
    displacement [m], ``R`` delta rotation row-major, ``angle`` its angle, ``qp`` prismatic joint
    value, ``s, v = sin(qr), 1 - cos(qr)`` of the revolute joint value ``qr``, ``et, er`` by how
    many sigmas the displacement and the rotation exceed the rigid test at ``rigid_test_sigmas``),
    then ``qr`` and the frame index.
    """

    def __init__(self, capacity: int, rigid_test_sigmas: float = 2.5) -> None:
        if capacity < 2 or capacity % 2:
            raise ValueError(f"capacity must be even and >= 2, got {capacity}")
        self.capacity = capacity
        self.rigid_test_sigmas = rigid_test_sigmas
        self.data: Array = np.zeros((capacity, _NCOL))
        self.n = 0
        self.stride = 1
        self.frames_seen = 0
        self._version = 0  # bumped on every change of the stored samples
        self._cache: tuple[int, int, Array, Array] = (-1, -1, self.data[:0], np.zeros(_NFEAT))

    def offer(self, d: Array, R: Array, q_prismatic: float, q_revolute: float,
              d2_translation: float = 0.0, d2_rotation: float = 0.0) -> bool:
        """Offer the next frame's hand displacement ``d`` (3,) [m] and delta rotation ``R`` (3x3),
        with the squared Mahalanobis distances of ``d`` and of the rotation vector of ``R``
        against the published covariance (the rigid test, docs/estimation.md#rigid-test).

        Stored only if the frame index is on the stride; returns whether it was stored.
        """
        k = self.frames_seen
        self.frames_seen += 1
        if k % self.stride:
            return False
        if self.n == self.capacity:
            self._decimate()
        d0, d1, d2 = d.tolist()
        r = R.ravel().tolist()
        s0, s1, s2 = r[7] - r[5], r[2] - r[6], r[3] - r[1]
        angle = math.atan2(0.5 * math.sqrt(s0 * s0 + s1 * s1 + s2 * s2),
                           0.5 * (r[0] + r[4] + r[8] - 1.0))
        qp = q_prismatic
        s = math.sin(q_revolute)
        v = 1.0 - math.cos(q_revolute)
        dd = d0 * d0 + d1 * d1 + d2 * d2
        x_t = self._excess_sigmas(d2_translation)
        x_r = self._excess_sigmas(d2_rotation)
        self.data[self.n] = (
            [1.0, d0, d1, d2, dd, angle * angle, qp, qp * qp,
             qp * d0, qp * d1, qp * d2, s, v, s * d0, s * d1, s * d2, v * d0, v * d1, v * d2]
            + r + [s * x for x in r] + [v * x for x in r]
            + [x_t * x_t, x_r * x_r, q_revolute, float(k)])
        self.n += 1
        self._version += 1
        return True

    def _excess_sigmas(self, mahalanobis2: float) -> float:
        """``max(0, sqrt(mahalanobis2) - rigid_test_sigmas)``
        (:func:`~services.kinematics.filters.excess_sigmas`)."""
        m = math.sqrt(mahalanobis2) if mahalanobis2 > 0.0 else 0.0
        return m - self.rigid_test_sigmas if m > self.rigid_test_sigmas else 0.0

    def _decimate(self) -> None:
        """Keep every other sample (frames 0, 2s, 4s, ...) and double the stride."""
        half = self.capacity // 2
        self.data[:half] = self.data[0:self.capacity:2]
        self.n = half
        self.stride *= 2
        self._version += 1

    def sample_indices(self, num: int) -> NDArray[np.intp]:
        """OMIP's uniform sample ``k_j = round(j max(1, n / num))``, ``j = 0..min(n, num)-1``."""
        m = min(self.n, num)
        step = max(1.0, self.n / num)
        return np.floor(np.arange(m) * step + 0.5).astype(np.intp)

    def samples(self, num: int) -> tuple[Array, Array]:
        """Feature rows (m x 48) at :meth:`sample_indices` and their column sums (48,), cached
        until the stored samples change."""
        version, num_cached, F, total = self._cache
        if version == self._version and num_cached == num:
            return F, total
        rows = self.data[:self.n] if self.n <= num else self.data[self.sample_indices(num)]
        F = rows[:, :_NFEAT]
        total = F.sum(axis=0)
        self._cache = (self._version, num, F, total)
        return F, total

    @property
    def d(self) -> Array:
        """Hand displacements (n, 3) [m]."""
        return self.data[:self.n, _D]

    @property
    def R_flat(self) -> Array:
        """Delta rotations (n, 9), row-major."""
        return self.data[:self.n, _R]

    @property
    def trace(self) -> Array:
        """Traces of the delta rotations (n,)."""
        R = self.data[:self.n, _R]
        return R[:, 0] + R[:, 4] + R[:, 8]

    @property
    def rigid_errors2(self) -> tuple[Array, Array]:
        """Squared excesses (n,) over the rigid test of the displacement and of the rotation
        [sigmas^2]."""
        return self.data[:self.n, _RT2], self.data[:self.n, _RR2]

    @property
    def q_prismatic(self) -> Array:
        return self.data[:self.n, _QP]

    @property
    def q_revolute(self) -> Array:
        return self.data[:self.n, _QR]

    @property
    def frame(self) -> Array:
        """Frame index (since t0) of each stored sample."""
        return self.data[:self.n, _FRAME]

    def _set_prismatic(self, q: Array) -> None:
        n = self.n
        X = self.data[:n]
        X[:, _QP] = q
        X[:, _QP2] = q * q
        X[:, _QPD] = q[:, None] * X[:, _D]
        self._version += 1

    def _set_revolute(self, q: Array) -> None:
        n = self.n
        X = self.data[:n]
        s = np.sin(q)
        v = 1.0 - np.cos(q)
        X[:, _QR] = q
        X[:, _SIN] = s
        X[:, _VERS] = v
        X[:, _SD] = s[:, None] * X[:, _D]
        X[:, _VD] = v[:, None] * X[:, _D]
        X[:, _SR] = s[:, None] * X[:, _R]
        X[:, _VR] = v[:, None] * X[:, _R]
        self._version += 1

    def backfill_prismatic(self, u: Array) -> None:
        """Joint values of samples stored before the prismatic filter started: ``q_k = d_k . u``."""
        self._set_prismatic(self.data[:self.n, _D] @ u)

    def backfill_revolute(self, u: Array) -> None:
        """Joint values before the revolute filter started: ``q_k = log(R_k) . u``.

        Those rotations are below the start threshold (well under pi), so the rotation vector is
        ``angle / (2 sin angle) * vee(R - R^T)`` (series for tiny angles).
        """
        n = self.n
        Rf = self.data[:n, _R]
        vee = np.stack([Rf[:, 7] - Rf[:, 5], Rf[:, 2] - Rf[:, 6], Rf[:, 3] - Rf[:, 1]], axis=1)
        angle = np.sqrt(self.data[:n, _ANG2])
        small = angle < 1e-6
        ratio = np.where(small, 0.5 + angle * angle / 12.0,
                         angle / (2.0 * np.where(small, 1.0, np.sin(angle))))
        self._set_revolute((ratio[:, None] * vee) @ u)

    def to_state(self) -> dict[str, Any]:
        """The stored samples and counters, for snapshots."""
        return {"capacity": self.capacity, "n": self.n, "stride": self.stride,
                "frames_seen": self.frames_seen, "data": self.data[:self.n].copy()}

    @classmethod
    def from_state(cls, state: dict[str, Any] | SnapshotReader, capacity: int | None = None,
                   rigid_test_sigmas: float = 2.5) -> DeltaHistory:
        """Rebuild from :meth:`to_state` (with ``capacity``, if given, the one it must have);
        SnapshotError naming the field for a value :meth:`to_state` cannot have written."""
        r = state if isinstance(state, SnapshotReader) else SnapshotReader(state, "history")
        cap = r.integer("capacity", 2, capacity)
        if cap % 2 or (capacity is not None and cap != capacity):
            raise SnapshotError(f"{r.path}.capacity: {cap} is not the configured "
                                f"history_capacity {capacity}")
        h = cls(cap, rigid_test_sigmas)
        h.frames_seen = r.integer("frames_seen", 0)
        h.n = r.integer("n", 0, min(cap, h.frames_seen))
        h.stride = r.integer("stride", 1, max(1, h.frames_seen))
        if h.stride & (h.stride - 1):
            raise SnapshotError(f"{r.path}.stride: {h.stride} is not a power of 2")
        h.data[:h.n] = r.array("data", (h.n, _NCOL))
        return h


def log_density(e_t: Array, e_r: Array, sigma_t: float, sigma_r: float) -> Array:
    """Per-sample ``log(N1(e_t; 0, sigma_t) N1(e_r; 0, sigma_r))`` with the pdf normalisers."""
    a = e_t / sigma_t
    b = e_r / sigma_r
    return -0.5 * (a * a + b * b) - (_LOG_2PI + math.log(sigma_t * sigma_r))


def log_normal_pdf(x: float, sigma: float) -> float:
    """``log N1(x; 0, sigma)``."""
    return -0.5 * (x / sigma) ** 2 - math.log(sigma) - 0.5 * _LOG_2PI


def softmax(log_scores: Array) -> Array:
    """Normalised probabilities from log scores (``-inf`` allowed; at least one finite)."""
    w = np.exp(log_scores - np.max(log_scores))
    return w / w.sum()


def point_line_distance(point: Array, line_point: Array, line_dir: Array) -> float:
    """Distance from ``point`` to the line ``line_point + s line_dir`` (unit direction)."""
    d = point - line_point
    d = d - float(d @ line_dir) * line_dir
    return math.sqrt(float(d @ d))


class ModelSelector:
    """History and log scores over ``JOINT_TYPES`` (rigid, prismatic, revolute, disconnected)."""

    def __init__(self, config: KinematicsConfig) -> None:
        self.config = config
        self.history = DeltaHistory(config.history_capacity, config.rigid_test_sigmas)
        self._log_priors = [math.log(p) if p > 0.0 else -math.inf
                            for p in (config.prior_rigid, config.prior_prismatic,
                                      config.prior_revolute, config.prior_disconnected)]
        self._log_disconnected = math.log(config.disconnected_density)
        st, sr = config.likelihood_sigma_translation_m, config.likelihood_sigma_rotation_rad
        self._kt = 0.5 / (st * st)  # log l = -kt e_t^2 - kr e_r^2 - c
        self._kr = 0.5 / (sr * sr)
        self._c = _LOG_2PI + math.log(st * sr)
        self._aggregation = config.likelihood_aggregation
        eps = config.likelihood_outlier_weight
        self._log_inlier = math.log1p(-eps)
        self._log_outlier = math.log(eps) + self._log_disconnected

    def add(self, d: Array, R: Array, q_prismatic: float, q_revolute: float,
            d2_translation: float = 0.0, d2_rotation: float = 0.0) -> None:
        """Record a frame: hand displacement ``d`` (3,) [m], delta rotation ``R`` (3x3), the joint
        values after the frame's correction, and the squared Mahalanobis distances of ``d`` and of
        the rotation vector of ``R`` against the published covariance (the rigid test)."""
        self.history.offer(d, R, q_prismatic, q_revolute, d2_translation, d2_rotation)

    def effective_samples(self, m: int, duration_s: float) -> float:
        """Independent samples that ``m`` samples over ``duration_s`` are worth ("tempered"):
        one per ``likelihood_correlation_time_s``, at least 1 and at most ``m``."""
        return min(float(m), max(1.0, duration_s / self.config.likelihood_correlation_time_s))

    def log_scores(self, prismatic: PrismaticJoint | None, revolute: RevoluteJoint | None,
                   hand_position: Array, reference_position: Array,
                   duration_s: float = 0.0) -> Array:
        """Unnormalised log scores (4,) in ``JOINT_TYPES`` order.

        ``hand_position`` (3,): the current hand origin in ``frame`` [m] (revolute distance prior);
        ``reference_position`` (3,): the hand origin of the measured reference pose [m];
        ``duration_s``: time since the reference pose ("tempered": the effective sample count).

        Fused form of the filters' ``history_errors``: for each hypothesis a coefficient vector
        ``c`` over the sample features gives ``-log N_j = kt e_t^2 + kr e_r^2 + log(2 pi st sr) =
        f_j . c`` (the revolute rotation error enters per sample, through its arccos), so the
        "product" log likelihood is a dot product with the feature sums.
        """
        F, total = self.history.samples(self.config.likelihood_sample_num)
        m = len(F)
        kt, kr = self._kt, self._kr
        lp = self._log_priors
        out = [-math.inf, -math.inf, -math.inf, 0.0]
        C = np.zeros((_NFEAT, 3))
        C[_ONE] = self._c
        C[_RT2, 0] = 0.5  # rigid: standardised errors beyond the rigid test
        C[_RR2, :2] = 0.5  # rigid and prismatic: the rotation beyond the rigid test
        if prismatic is not None:
            # e_t^2 = |d - o - qp u|^2 = |d|^2 - 2 d.o + |o|^2 + qp^2 - 2 qp d.u + 2 qp u.o
            u0, u1, u2 = prismatic.u.tolist()
            o0, o1, o2 = prismatic.o.tolist()
            k2 = -2.0 * kt
            C[:_QPD.stop, 1] = (self._c + kt * (o0 * o0 + o1 * o1 + o2 * o2), k2 * o0, k2 * o1,
                                k2 * o2, kt, 0.0, -k2 * (u0 * o0 + u1 * o1 + u2 * o2), kt,
                                k2 * u0, k2 * u1, k2 * u2)
        er2: Array | None = None
        rev_prior = 0.0
        if revolute is not None:
            er2, coef = self._revolute_terms(F, revolute, reference_position)
            C[:_NFEAT_T, 2] = coef
            d_axis = point_line_distance(hand_position, revolute.p, revolute.u)
            rev_prior = lp[2] + log_normal_pdf(d_axis, self.config.revolute_max_joint_distance_m)
        if self._aggregation == "product":
            neg = (total @ C).tolist()  # sums over the samples of -log N_j
            out[0] = lp[0] - neg[0]
            if prismatic is not None:
                out[1] = lp[1] - neg[1]
            if er2 is not None:
                out[2] = rev_prior - neg[2] - kr * float(er2.sum())
            out[3] = lp[3] + m * self._log_disconnected
            return np.array(out)
        L = -(F @ C)  # (m, 3) per-sample log densities
        if er2 is not None:
            L[:, 2] -= kr * er2
        if self._aggregation == "tempered":
            # log((1 - eps) N_j + eps c): the sample is explained, or it is an outlier that the
            # hypothesis explains no better than disconnected does.
            mix = np.logaddexp(L + self._log_inlier, self._log_outlier)
            n_eff = self.effective_samples(m, duration_s)
            agg = (mix.sum(axis=0) * (n_eff / m)).tolist()
            out[3] = lp[3] + n_eff * self._log_disconnected
        else:  # "mean": log of the arithmetic mean (OMIP)
            mx = L.max(axis=0)
            agg = (mx + np.log(np.exp(L - mx).mean(axis=0))).tolist()
            out[3] = lp[3] + self._log_disconnected
        out[0] = lp[0] + agg[0]
        if prismatic is not None:
            out[1] = lp[1] + agg[1]
        if er2 is not None:
            out[2] = rev_prior + agg[2]
        return np.array(out)

    def _revolute_terms(self, F: Array, revolute: RevoluteJoint,
                        c0: Array) -> tuple[Array, list[float]]:
        """Per-sample squared rotation errors (m,) and the translation coefficients (features
        ``0.._VD``) of the revolute hypothesis.

        The hypothesis moves the hand by ``g + s Ka + v K^2a`` (``K = [u]x``, ``c0' = E c0``,
        ``g = c0' - c0``, ``a = c0' - p``; see ``RevoluteJoint.history_errors``). With
        ``Ka _|_ K^2a``, ``|Ka| = |K^2a| = rho`` and ``s^2 + v^2 = 2 v``:
        ``e_t^2 = |d|^2 - 2 d.g + |g|^2 + 2 s (g.Ka - d.Ka) + 2 v (g.K^2a + rho^2 - d.K^2a)``.
        ``cos e_r = (<R_j, R_E> + s <R_j, K R_E> + v <R_j, K^2 R_E> - 1) / 2``.
        """
        kt = self._kt
        u0, u1, u2 = revolute.u.tolist()
        p0, p1, p2 = revolute.p.tolist()
        (r00, r01, r02, t0), (r10, r11, r12, t1), (r20, r21, r22, t2) = revolute.E[:3].tolist()
        x0, x1, x2 = c0.tolist()
        c00 = r00 * x0 + r01 * x1 + r02 * x2 + t0  # c0' = E c0
        c01 = r10 * x0 + r11 * x1 + r12 * x2 + t1
        c02 = r20 * x0 + r21 * x1 + r22 * x2 + t2
        g0, g1, g2 = c00 - x0, c01 - x1, c02 - x2
        a0, a1, a2 = c00 - p0, c01 - p1, c02 - p2
        ka0, ka1, ka2 = u1 * a2 - u2 * a1, u2 * a0 - u0 * a2, u0 * a1 - u1 * a0  # K a
        kk0, kk1, kk2 = u1 * ka2 - u2 * ka1, u2 * ka0 - u0 * ka2, u0 * ka1 - u1 * ka0  # K^2 a
        k2 = -2.0 * kt
        coef = [self._c + kt * (g0 * g0 + g1 * g1 + g2 * g2), k2 * g0, k2 * g1, k2 * g2, kt,
                0.0, 0.0, 0.0, 0.0, 0.0, 0.0,
                -k2 * (g0 * ka0 + g1 * ka1 + g2 * ka2),
                -k2 * (g0 * kk0 + g1 * kk1 + g2 * kk2 + ka0 * ka0 + ka1 * ka1 + ka2 * ka2),
                k2 * ka0, k2 * ka1, k2 * ka2, k2 * kk0, k2 * kk1, k2 * kk2]
        # Columns of R_E, K R_E (= u x col), K^2 R_E, flattened row-major into w (27).
        cols = ((r00, r10, r20), (r01, r11, r21), (r02, r12, r22))
        kc = [(u1 * z - u2 * y, u2 * x - u0 * z, u0 * y - u1 * x) for x, y, z in cols]
        kkc = [(u1 * z - u2 * y, u2 * x - u0 * z, u0 * y - u1 * x) for x, y, z in kc]
        w = np.array([r00, r01, r02, r10, r11, r12, r20, r21, r22]
                     + [kc[j][i] for i in range(3) for j in range(3)]
                     + [kkc[j][i] for i in range(3) for j in range(3)])
        er = np.arccos(np.clip((F[:, _R.start:_VR.stop] @ w - 1.0) * 0.5, -1.0, 1.0))
        return er * er, coef

    def to_state(self) -> dict[str, Any]:
        """The history, for snapshots."""
        return {"history": self.history.to_state()}

    @classmethod
    def from_state(cls, config: KinematicsConfig,
                   state: dict[str, Any] | SnapshotReader) -> ModelSelector:
        """Rebuild from :meth:`to_state`; SnapshotError naming the field for a value
        :meth:`to_state` cannot have written."""
        r = state if isinstance(state, SnapshotReader) else SnapshotReader(state, "selector")
        s = cls(config)
        s.history = DeltaHistory.from_state(r.map("history"), config.history_capacity,
                                            config.rigid_test_sigmas)
        return s


__all__ = [
    "JOINT_TYPES",
    "DeltaHistory",
    "ModelSelector",
    "log_density",
    "log_normal_pdf",
    "point_line_distance",
    "softmax",
]
