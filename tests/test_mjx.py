"""MuJoCo MJX coupling: ``jaxpose.dynamics.mjx.MJXSystem`` and the MJX learning example.

* The System's step equals MuJoCo's own C engine (``mujoco.mj_step``) on the example's
  pendulum, with the learnable parameters bound (``bind``) compared against a MuJoCo model
  compiled from MJCF with those values (so the inertia scaling is checked by MuJoCo), and
  its observations equal ``mj_forward``'s sensor data.
* The example (EKF likelihood through MJX, Adam in one jitted ``lax.scan``) runs end to end
  at small sizes and learns; slow tests check its gradient against central differences
  (EKF and UKF) and the full-size run's estimates against the truth.
* ``import jaxpose`` works without mujoco.

Skipped (except the import check) when mujoco / mujoco-mjx are not installed
(``pip install .[mjx]``).
"""

from __future__ import annotations

import io
import subprocess
import sys
from contextlib import redirect_stdout
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def mj():
    mujoco = pytest.importorskip("mujoco")
    pytest.importorskip("mujoco.mjx")
    jax.config.update("jax_enable_x64", True)
    return mujoco


@pytest.fixture(scope="module")
def example(mj):
    from notebooks._examples import mjx_learning

    return mjx_learning


def test_import_jaxpose_without_mujoco():
    code = (
        "import sys; sys.modules['mujoco'] = None\n"
        "import jaxpose, jaxpose.dynamics.mjx as m\n"
        "try:\n"
        "    m.MJXSystem.from_xml('<mujoco/>')\n"
        "except ImportError as e:\n"
        "    print('ImportError:', e)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                         text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "ImportError:" in out.stdout


def test_notebook_is_built_from_the_example():
    from notebooks._examples import mjx_notebook

    path = ROOT / "notebooks" / "mjx_learning.ipynb"
    assert path.read_text(encoding="utf-8") == mjx_notebook.render(), (
        f"{path} is stale: run python notebooks/_examples/mjx_notebook.py"
    )


def _native_rollout(mujoco, xml: str, x0: np.ndarray, us: np.ndarray) -> np.ndarray:
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    data.qpos[:], data.qvel[:] = x0[: model.nq], x0[model.nq :]
    xs = [x0]
    for u in us:
        data.ctrl[:] = u
        mujoco.mj_step(model, data)
        xs.append(np.concatenate([data.qpos, data.qvel]))
    return np.stack(xs)


def test_step_equals_mujoco_with_bound_parameters(mj, example):
    from jaxpose.dynamics import rollout

    truth = {"damping": 0.4, "mass": 1.6}
    system = example.make_system(**example.GUESS)  # built with other parameters
    bound = system.__class__(system.model, system.data, {k: jnp.asarray(v) for k, v in
                             truth.items()}, system.bind, system.substeps, system.observe)
    rng = np.random.default_rng(0)
    x0 = np.array([0.7, -0.3])
    us = rng.normal(0.0, 1.5, (60, 1))
    xs = np.asarray(jax.jit(lambda x, u: rollout(bound, x, u)[0])(x0, us))
    xml = example.PENDULUM_XML.replace('damping="0.1"', f'damping="{truth["damping"]}"')
    xml = xml.replace('mass="1"', f'mass="{truth["mass"]}"')
    ref = _native_rollout(mj, xml, x0, us)
    assert np.max(np.abs(ref[-1] - x0)) > 0.1  # it moved
    np.testing.assert_allclose(xs, ref, rtol=0, atol=1e-10)
    # the guess's model differs: the parameters matter
    other = _native_rollout(mj, example.PENDULUM_XML.replace('mass="1"', 'mass="0.6"').replace(
        'damping="0.1"', 'damping="0.05"'), x0, us)
    assert np.max(np.abs(other - ref)) > 1e-2
    assert bound.state_dim == 2 and bound.input_dim == 1
    assert float(bound.dt) == pytest.approx(0.01)


SENSOR_XML = """
<mujoco>
  <option timestep="0.005"/>
  <worldbody>
    <body name="cart">
      <joint name="slide" type="slide" axis="1 0 0" damping="0.2"/>
      <geom type="box" size="0.2 0.1 0.05" mass="1"/>
      <body name="pole">
        <joint name="hinge" type="hinge" axis="0 1 0"/>
        <geom type="capsule" fromto="0 0 0 0 0 0.6" size="0.03" mass="0.2"/>
      </body>
    </body>
  </worldbody>
  <actuator><motor joint="slide"/></actuator>
  <sensor>
    <jointpos joint="hinge"/><jointvel joint="slide"/><framepos objtype="body" objname="pole"/>
  </sensor>
</mujoco>
"""


def test_cartpole_substeps_and_sensor_observation(mj):
    from jaxpose.dynamics.mjx import MJXSystem

    sysm = MJXSystem.from_xml(SENSOR_XML, substeps=3, observe="sensordata")
    x = np.array([0.1, 0.3, -0.2, 0.5])
    u = np.array([0.7])
    f = jax.jit(lambda x, u: (sysm.state_transition(x, u, 2), sysm.observation(x, u, 2)))
    x1, y = map(np.asarray, f(x, u))
    model = mj.MjModel.from_xml_string(SENSOR_XML)
    data = mj.MjData(model)
    data.qpos[:], data.qvel[:], data.ctrl[:] = x[:2], x[2:], u
    mj.mj_forward(model, data)
    np.testing.assert_allclose(y, data.sensordata, rtol=0, atol=1e-12)
    for _ in range(3):
        mj.mj_step(model, data)
    np.testing.assert_allclose(x1, np.concatenate([data.qpos, data.qvel]), rtol=0, atol=1e-10)
    assert float(sysm.dt) == pytest.approx(0.015)
    # qpos observation and bad input
    q = MJXSystem(sysm.model, sysm.data, observe="qpos")
    np.testing.assert_array_equal(q.observation(jnp.asarray(x), jnp.asarray(u)), x[:2])
    with pytest.raises(ValueError, match=r"x: expected shape \(4,\)"):
        sysm.state_transition(jnp.zeros(3), jnp.zeros(1))
    with pytest.raises(ValueError, match=r"u: expected shape \(1,\)"):
        sysm.state_transition(jnp.zeros(4), jnp.zeros(2))
    with pytest.raises(ValueError, match="observe"):
        MJXSystem(sysm.model, sysm.data, observe="pixels")
    with pytest.raises(ValueError, match="substeps"):
        MJXSystem(sysm.model, sysm.data, substeps=0)
    with pytest.raises(ValueError, match="without bind"):
        MJXSystem(sysm.model, sysm.data, params={"damping": jnp.ones(())})
    with pytest.raises(TypeError, match="mjx.Model"):
        MJXSystem(model, sysm.data)  # a native MjModel, not an MJX one


def test_example_end_to_end_small(example):
    out = io.StringIO()
    with redirect_stdout(out):
        hist = example.main(["--steps", "15", "--horizon", "40", "--batch", "2"])
    text = out.getvalue()
    assert "Adam steps (EKF likelihood)" in text and "truth" in text
    loss, damping, mass = (np.asarray(a) for a in (hist.loss, hist.damping, hist.mass))
    assert loss.shape == (15,) and damping.shape == mass.shape == (16,)
    assert np.all(np.isfinite(loss)) and np.all(np.isfinite(mass))
    assert loss[-1] < loss[0] - 0.05  # the likelihood improves
    err0 = abs(mass[0] - hist.truth["mass"])
    assert abs(mass[-1] - hist.truth["mass"]) < 0.7 * err0  # the mass moves to the truth
    assert damping[0] == pytest.approx(example.GUESS["damping"])


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["ekf", "ukf"])
def test_example_gradient_matches_central_differences(example, kind):
    data = example.simulate(example.make_system(**example.TRUE), jax.random.PRNGKey(1), 2, 30)
    f = jax.jit(example.objective(data, example.make_system(**example.GUESS), kind))
    theta = jnp.log(jnp.array([0.2, 1.0]))
    _, g = f(theta)
    h = 1e-5
    fd = [(float(f(theta + h * e)[0]) - float(f(theta - h * e)[0])) / (2 * h)
          for e in np.eye(2)]
    np.testing.assert_allclose(np.asarray(g), fd, rtol=1e-5, atol=1e-8)


@pytest.mark.slow
def test_example_full_run_recovers_parameters(example):
    hist = example.train()
    assert abs(float(hist.mass[-1]) - hist.truth["mass"]) < 0.05 * hist.truth["mass"]
    assert abs(float(hist.damping[-1]) - hist.truth["damping"]) < 0.1 * hist.truth["damping"]
