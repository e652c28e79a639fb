"""predict_hand_pose: reproduces the demonstrated hand poses, extrapolates with dq, propagates the
model covariance with the exact Jacobian, and is duck-typed on the wire model's field names."""

from __future__ import annotations

import math
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from services.common import se3
from services.kinematics.estimator import KinematicBelief, KinematicEstimator
from services.kinematics.filters import rotate_axis, tangent_basis
from services.kinematics.prediction import predict_hand_pose
from tests.kinematics import Sample, demo, prismatic_joint, revolute_joint, unit

Array = np.ndarray


def _run(samples: list[Sample]) -> KinematicBelief:
    est = KinematicEstimator()
    for s in samples:
        b = est.update(*s)
    return b


@pytest.mark.parametrize("kind", ["prismatic", "revolute"])
def test_reproduces_and_extrapolates_the_demonstration(kind: str) -> None:
    if kind == "prismatic":
        joint, q_max = prismatic_joint([0.3, -0.2, 0.9], [0.1, 0.05, 0.6]), 0.12
    else:
        joint, q_max = revolute_joint([0.1, 1.0, 0.2], [0.2, -0.1, 0.7], 0.10), math.pi / 2
    samples = demo(joint, q_max, duration_s=2.0)
    n = 45  # stop mid-motion, where the velocity is large
    b = _run(samples[:n])
    assert b.type == kind
    out = predict_hand_pose(b, b.stamp_ns)
    assert out is not None
    T, cov = out
    np.testing.assert_allclose(T, samples[n - 1][1], atol=1e-4)
    assert cov.shape == (6, 6) and np.allclose(cov, cov.T)
    assert np.linalg.eigvalsh(cov).min() > -1e-15
    # One frame ahead: q + dq dt follows the motion (min-jerk, so only to first order).
    ahead = predict_hand_pose(b, samples[n][0])
    assert ahead is not None
    err_pred = np.linalg.norm(se3.se3_log(ahead[0] @ se3.se3_inverse(samples[n][1])))
    err_static = np.linalg.norm(se3.se3_log(T @ se3.se3_inverse(samples[n][1])))
    assert err_pred < 0.2 * err_static


def test_rigid_unknown_disconnected() -> None:
    T_ref = se3.se3_exp(np.array([0.1, 0.2, 0.6, 0.3, -0.2, 0.1]))
    belief = SimpleNamespace(type="rigid", reference_pose=T_ref, stamp_ns=5, prismatic=None,
                             revolute=None)
    out = predict_hand_pose(belief, 10**9)
    assert out is not None
    np.testing.assert_array_equal(out[0], T_ref)
    np.testing.assert_array_equal(out[1], np.zeros((6, 6)))
    for kind in ("unknown", "disconnected"):
        belief.type = kind
        assert predict_hand_pose(belief, 10**9) is None
    belief.type = "revolute"  # parameters missing
    assert predict_hand_pose(belief, 10**9) is None


def _model(kind: str, rng: np.random.Generator) -> SimpleNamespace:
    axis = unit(rng.normal(size=3))
    A = rng.normal(size=(7, 7)) * 0.05
    if kind == "prismatic":
        params = SimpleNamespace(axis=axis.tolist(), q=0.05, dq=0.1, covariance=(A @ A.T)[:4, :4])
    else:
        point = rng.normal(size=3)
        point -= (point @ axis) * axis
        params = SimpleNamespace(axis=axis, point=point, q=2.5, dq=-0.4, covariance=A @ A.T)
    return SimpleNamespace(type=kind, reference_pose=se3.se3_exp(rng.normal(size=6)),
                           stamp_ns=10**9, prismatic=params if kind == "prismatic" else None,
                           revolute=params if kind == "revolute" else None)


def _pose_from(kind: str, m: Any, d: Array, stamp_ns: int) -> Array:
    """The predicted pose with the published parameters perturbed by ``d``."""
    p = m.prismatic if kind == "prismatic" else m.revolute
    u = np.asarray(p.axis, dtype=float)
    u2 = rotate_axis(u, tangent_basis(u), d[:2])[0]
    dt = (stamp_ns - m.stamp_ns) * 1e-9
    if kind == "prismatic":
        q = p.q + d[2] + (p.dq + d[3]) * dt
        D = np.eye(4)
        D[:3, 3] = q * u2
    else:
        point = p.point + d[2:5]
        q = p.q + d[5] + (p.dq + d[6]) * dt
        D = se3.se3_exp(q * np.concatenate([np.cross(point, u2), u2]))
    return D @ m.reference_pose


@pytest.mark.parametrize("kind", ["prismatic", "revolute"])
def test_covariance_is_the_exact_jacobian_propagation(kind: str) -> None:
    rng = np.random.default_rng(0)
    m = _model(kind, rng)
    stamp = m.stamp_ns + 250_000_000
    out = predict_hand_pose(m, stamp)
    assert out is not None
    T, cov = out
    n = 4 if kind == "prismatic" else 7
    np.testing.assert_allclose(T, _pose_from(kind, m, np.zeros(n), stamp), atol=1e-12)
    T_inv = se3.se3_inverse(T)
    eps = 1e-6
    J = np.zeros((6, n))
    for i in range(n):
        e = np.zeros(n)
        e[i] = eps
        J[:, i] = (se3.se3_log(_pose_from(kind, m, e, stamp) @ T_inv)
                   - se3.se3_log(_pose_from(kind, m, -e, stamp) @ T_inv)) / (2 * eps)
    C = m.prismatic.covariance if kind == "prismatic" else m.revolute.covariance
    np.testing.assert_allclose(cov, J @ C @ J.T, atol=1e-9)


def test_accepts_the_wire_model() -> None:
    protocol = pytest.importorskip("services.common.protocol")
    joint = revolute_joint([0.0, 0.6, 0.8], [0.1, 0.0, 0.6], 0.1)
    samples = demo(joint, 1.0, duration_s=1.0)
    b = _run(samples)
    assert b.revolute is not None
    wire = protocol.KinematicModel(
        seq=0, stamp_ns=b.stamp_ns, frame_id=b.frame_id, type=b.type,
        probabilities=dict(b.probabilities),
        revolute=protocol.RevoluteParams(axis=np.array(b.revolute.axis),
                                         point=np.array(b.revolute.point), q=b.revolute.q,
                                         dq=b.revolute.dq,
                                         covariance=np.array(b.revolute.covariance)),
        reference_pose=np.array(b.reference_pose), updates=b.updates)
    wire = protocol.KinematicModel.from_msgpack(wire.to_msgpack())
    a, w = predict_hand_pose(b, b.stamp_ns + 10**7), predict_hand_pose(wire, b.stamp_ns + 10**7)
    assert a is not None and w is not None
    np.testing.assert_allclose(a[0], w[0], atol=1e-12)
    np.testing.assert_allclose(a[1], w[1], atol=1e-15)
