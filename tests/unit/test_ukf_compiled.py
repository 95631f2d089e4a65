"""The compiled UKF kernel: its loops equal their plain-Python source and the numpy kernel on
random states, a non-SPD covariance is reported (not raised inside the loop), and without numba
the filter falls back to the numpy kernel."""

from __future__ import annotations

import numpy as np
import pytest

from estimator import Ukf, compiled
from estimator.kernels import CompiledKernel, FastKernel
from estimator.quaternion import quat_conj, quat_normalize

GRAVITY_W = np.array([0.0, 0.0, -9.81])


def _random_state(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    x = rng.normal(0.0, 0.05, 15)
    A = rng.normal(0.0, 0.01, (15, 15))
    P = A @ A.T + 1e-6 * np.eye(15)
    q = quat_normalize(rng.normal(size=4))
    return x, P, q


@pytest.mark.parametrize("seed", range(5))
def test_that_compiled_predict_and_update_equal_the_numpy_kernel(seed: int) -> None:
    # Fixture
    rng = np.random.default_rng(seed)
    fast = CompiledKernel(15, 1e-3, 2.0, 0.0, GRAVITY_W)
    ref = FastKernel(15, 1e-3, 2.0, 0.0, GRAVITY_W)
    x, P, q = _random_state(rng)
    Q = 1e-8 * np.eye(15)
    gyro, accel = rng.normal(0.0, 1.0, 3), rng.normal(0.0, 3.0, 3) + np.array([0, 0, 9.81])
    q_next = quat_normalize(rng.normal(size=4))
    z, R = rng.normal(0.0, 0.01, 6), 1e-6 * np.eye(6)
    # Test
    got = fast.predict(x, P, Q, 0.002, gyro, accel, q, quat_conj(q_next))
    want = ref.predict(x, P, Q, 0.002, gyro, accel, q, quat_conj(q_next))
    got_u = fast.update(x, P, z, R)
    want_u = ref.update(x, P, z, R)
    # Assert: rounding only; with alpha = 1e-3 the mean weights are ~1e6 with alternating
    # signs, so another summation order moves a mean by ~1e-16 * 1e6 (the filter's 1e-9 bar)
    for a, b in zip((*got, *got_u), (*want, *want_u), strict=True):
        np.testing.assert_allclose(a, b, rtol=0.0, atol=1e-9)


def test_that_the_jitted_loops_equal_their_python_source() -> None:
    # Fixture: the plain-Python functions are what runs where numba is absent
    if not compiled.AVAILABLE:
        pytest.skip("numba not installed: the Python source is all there is")
    rng = np.random.default_rng(7)
    k = CompiledKernel(15, 1e-3, 2.0, 0.0, GRAVITY_W)
    x, P, q = _random_state(rng)
    Q = 1e-8 * np.eye(15)
    gyro, accel = rng.normal(0.0, 1.0, 3), np.array([0.1, -0.2, 9.7])
    outs = []
    py_func = compiled.predict_step.py_func  # type: ignore[attr-defined]
    for fn in (compiled.predict_step, py_func):
        bufs = (np.empty((31, 15)), np.empty((15, 15)), np.empty((15, 15)), np.empty((15, 31)),
                np.empty(4), np.empty(15), np.empty((15, 15)), np.empty(4))
        status = fn(x, P, Q, 0.002, gyro, accel, q, GRAVITY_W, k.Wm, k.Wc, k.scale, 1e-12,
                    0.25, *bufs)
        outs.append((status, bufs[5], bufs[6], bufs[7]))
    # Assert
    assert outs[0][0] == outs[1][0] == 0
    for a, b in zip(outs[0][1:], outs[1][1:], strict=True):
        np.testing.assert_allclose(a, b, rtol=0.0, atol=1e-13)


def test_that_a_covariance_that_is_not_positive_definite_is_reported() -> None:
    # Fixture
    k = CompiledKernel(15, 1e-3, 2.0, 0.0, GRAVITY_W)
    P = np.eye(15)
    P[4, 4] = -1.0
    q = np.array([1.0, 0.0, 0.0, 0.0])
    # Test / Assert
    assert k.predict_step(np.zeros(15), P, q, np.zeros((15, 15)), 0.002, np.zeros(3),
                          np.array([0.0, 0.0, 9.81]), 1e-12, 1.0) is None
    with pytest.raises(np.linalg.LinAlgError):
        k.predict(np.zeros(15), P, np.zeros((15, 15)), 0.002, np.zeros(3),
                  np.array([0.0, 0.0, 9.81]), q, q)


def test_that_without_numba_the_filter_uses_the_numpy_kernel(
        monkeypatch: pytest.MonkeyPatch) -> None:
    # Fixture
    monkeypatch.setattr(compiled, "AVAILABLE", False)
    # Test
    est = Ukf()
    # Assert
    assert est.kernel_name == "numpy"
    assert isinstance(est._kernel, FastKernel)


_NO_COMPILE_IN_TICKS = r"""
import json, numpy as np
from numba.core import event
from estimator import Ukf, EstimatorConfig, compiled
import numba

def dispatchers():
    return {n: f for n, f in vars(compiled).items()
            if isinstance(f, numba.core.registry.CPUDispatcher)}

ukf = Ukf(EstimatorConfig())     # start-up: compiles or loads every kernel here
before = {n: len(f.overloads) for n, f in dispatchers().items()}
with event.install_recorder("numba:compile") as rec:
    ukf.initialize(0.0, (0.0, 0.0, 1.0), (1.0, 0.0, 0.0, 0.0))
    for k in range(1, 400):         # as the loop feeds it: tuples, a late pose every 5th tick
        t = 0.002 * k
        ukf.predict(t, (0.01, -0.02, 0.0), (0.1, 0.0, 9.81), (0.0, 0.0, 14.0))
        if k % 5 == 0:
            # every 16th pose less late than the horizon: the filter advances to it
            late = 0.004 if k % 80 == 0 else 0.006
            ukf.update_pose(t - late, (0.0, 0.0, 1.0 + 1e-4), (1.0, 0.0, 0.0, 0.0))
        ukf.estimate()
after = {n: len(f.overloads) for n, f in dispatchers().items()}
print(json.dumps({"compiles": len(rec.buffer), "before": before, "after": after}))
"""


def test_that_no_tick_waits_on_a_compile() -> None:
    # Fixture: a fresh interpreter, so nothing compiled by other tests hides a lazy compile
    if not compiled.AVAILABLE:
        pytest.skip("numba not installed: nothing is compiled")
    import json
    import subprocess
    import sys
    out = subprocess.run([sys.executable, "-c", _NO_COMPILE_IN_TICKS], capture_output=True,
                         text=True, check=True, timeout=300)
    got = json.loads(out.stdout.strip().splitlines()[-1])
    # Assert: every kernel the ticks use was ready after the constructor (compiled or loaded
    # from the cache there), and 400 ticks with poses neither compiled nor loaded another
    assert got["compiles"] == 0
    assert got["after"] == got["before"]
    used = ("predict_step", "update_step", "predict", "update", "horizon_predict",
            "fuse_now", "advance", "fuse_in_past")
    assert all(got["before"][name] == 1 for name in used), got["before"]
