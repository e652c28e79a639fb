"""predict_hand_pose: reproduces the demonstrated hand poses, extrapolates with dq, propagates the
model covariance with the exact Jacobian, and predicts the same from the estimator's model before
and after the wire; predicted_pose is its pose alone."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from services.common import se3
from services.common.protocol import KinematicModel, PrismaticParams, RevoluteParams
from services.kinematics.estimator import KinematicEstimator
from services.kinematics.filters import rotate_axis, tangent_basis
from services.kinematics.prediction import predict_hand_pose, predicted_pose
from tests.kinematics import Sample, demo, prismatic_joint, revolute_joint, unit

Array = np.ndarray


PROBABILITIES = {"rigid": 0.25, "prismatic": 0.25, "revolute": 0.25, "disconnected": 0.25}


def _run(samples: list[Sample]) -> KinematicModel:
    est = KinematicEstimator()
    for s in samples:
        assert est.update(*s).model is not None
    return est.model


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
    rigid = KinematicModel(type="rigid", probabilities=PROBABILITIES, reference_pose=T_ref,
                           stamp_ns=5)
    out = predict_hand_pose(rigid, 10**9)
    assert out is not None
    np.testing.assert_array_equal(out[0], T_ref)
    np.testing.assert_array_equal(out[1], np.zeros((6, 6)))
    for kind in ("unknown", "disconnected"):
        assert predict_hand_pose(replace(rigid, type=kind), 10**9) is None
    # parameters missing
    assert predict_hand_pose(replace(rigid, type="revolute"), 10**9) is None


def _model(kind: str, rng: np.random.Generator) -> KinematicModel:
    axis = unit(rng.normal(size=3))
    A = rng.normal(size=(7, 7)) * 0.05
    prismatic = revolute = None
    if kind == "prismatic":
        prismatic = PrismaticParams(axis=axis, q=0.05, dq=0.1, covariance=(A @ A.T)[:4, :4])
    else:
        point = rng.normal(size=3)
        point -= (point @ axis) * axis
        revolute = RevoluteParams(axis=axis, point=point, q=2.5, dq=-0.4, covariance=A @ A.T)
    return KinematicModel(type=kind, probabilities=PROBABILITIES,
                          reference_pose=se3.se3_exp(rng.normal(size=6)), stamp_ns=10**9,
                          prismatic=prismatic, revolute=revolute)


def _pose_from(kind: str, m: KinematicModel, d: Array, stamp_ns: int) -> Array:
    """The predicted pose with the published parameters perturbed by ``d``."""
    p = m.prismatic if kind == "prismatic" else m.revolute
    assert p is not None
    u = np.asarray(p.axis, dtype=float)
    u2 = rotate_axis(u, tangent_basis(u), d[:2])[0]
    dt = (stamp_ns - m.stamp_ns) * 1e-9
    if kind == "prismatic":
        q = p.q + d[2] + (p.dq + d[3]) * dt
        D = np.eye(4)
        D[:3, 3] = q * u2
    else:
        assert isinstance(p, RevoluteParams)
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
    params = m.prismatic if kind == "prismatic" else m.revolute
    assert params is not None
    C = params.covariance
    np.testing.assert_allclose(cov, J @ C @ J.T, atol=1e-9)


def test_the_estimators_model_predicts_the_same_after_the_wire() -> None:
    joint = revolute_joint([0.0, 0.6, 0.8], [0.1, 0.0, 0.6], 0.1)
    b = _run(demo(joint, 1.0, duration_s=1.0))
    assert b.type == "revolute" and b.revolute is not None
    wire = KinematicModel.from_msgpack(b.to_msgpack())
    a, w = predict_hand_pose(b, b.stamp_ns + 10**7), predict_hand_pose(wire, b.stamp_ns + 10**7)
    assert a is not None and w is not None
    np.testing.assert_array_equal(a[0], w[0])  # the round trip keeps every bit
    np.testing.assert_array_equal(a[1], w[1])


def test_predicted_pose_is_the_pose_of_predict_hand_pose() -> None:
    rng = np.random.default_rng(4)
    for kind in ("prismatic", "revolute"):
        m = _model(kind, rng)
        for stamp in (m.stamp_ns, m.stamp_ns + 33_333_333, m.stamp_ns + 7 * 10**9):
            full = predict_hand_pose(m, stamp)
            assert full is not None
            np.testing.assert_array_equal(predicted_pose(m, stamp), full[0])
    T_ref = se3.se3_exp(np.array([0.1, 0.2, 0.6, 0.3, -0.2, 0.1]))
    rigid = KinematicModel(type="rigid", probabilities=PROBABILITIES, reference_pose=T_ref)
    np.testing.assert_array_equal(predicted_pose(rigid, 10**9), T_ref)
    for kind in ("unknown", "disconnected", "revolute"):  # revolute without its parameters
        assert predicted_pose(replace(rigid, type=kind), 10**9) is None
