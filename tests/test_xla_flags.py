"""The XLA:CPU options set at import: flag handling, that the filter's and smoother's scans
really are compiled into one kernel with the small-loop option (and not without it), and
that the solver compiles without YNNPACK fusions."""

from __future__ import annotations

import os
import subprocess
import sys

import jaxlib
import pytest

from jaxtraj import _xla

# Builds a short simulated stream, compiles the filter and prints whether XLA emitted the
# scan as one "small call" kernel. Run in a fresh interpreter: XLA reads XLA_FLAGS once.
_PROBE = """
import jax
jax.config.update("jax_enable_x64", True)
import jaxtraj
from jaxtraj.fusion import (ImuNoise, RobotNoise, build_events, eskf, initial_covariance,
                            initial_state, rts_smoother)
from jaxtraj.fusion.simulate import LissajousTrajectory, simulate_recording
rec = simulate_recording(jax.random.PRNGKey(0), LissajousTrajectory(), duration=0.3,
                         imu_noise=ImuNoise.xsens_mti(), robot_noise=RobotNoise.kuka_class())
ev = build_events(rec.imu, rec.robot, rec.image_times, noise=RobotNoise.kuka_class())
P0 = initial_covariance(1e-3, 0.05, 0.02, 0.1, 0.01)
res = eskf(ev, initial_state(ev), P0, ImuNoise.xsens_mti())
hlo = eskf.lower(ev, initial_state(ev), P0, ImuNoise.xsens_mti()).compile().as_text()
hlo2 = rts_smoother.lower(res, ImuNoise.xsens_mti()).compile().as_text()
print(hlo.count("xla_cpu_small_call"), hlo2.count("xla_cpu_small_call"))
"""


def _probe(env_update: dict[str, str]) -> str:
    # without the test session's compilation cache: the probe checks what XLA emits
    env = {
        k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "JAX_COMPILATION_CACHE_DIR")
    }
    # ... but with the session's optimisation level (conftest.py), which compiles faster and
    # does not change whether the loop becomes one kernel
    level = [f for f in os.environ.get("XLA_FLAGS", "").split() if "optimization_level" in f]
    if level:
        env["XLA_FLAGS"] = " ".join(level)
    env.update(env_update)
    out = subprocess.run(
        [sys.executable, "-c", _PROBE], env=env, capture_output=True, text=True, timeout=300
    )
    assert out.returncode == 0, out.stderr[-2000:]
    filter_calls, smoother_calls = map(int, out.stdout.strip().splitlines()[-1].split())
    return filter_calls, smoother_calls


def test_flag_is_appended_to_existing_flags():
    flags = _xla.with_small_loop_flag("--xla_force_host_platform_device_count=2")
    assert flags.startswith("--xla_force_host_platform_device_count=2 ")
    assert flags.endswith(
        f"--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold="
        f"{_xla.SMALL_LOOP_BYTES}"
    )
    assert _xla.with_small_loop_flag("") == flags.split(" ", 1)[1]


def test_users_backend_extra_options_win():
    mine = "--xla_backend_extra_options=xla_cpu_small_while_loop_byte_threshold=5"
    assert _xla.with_small_loop_flag(mine) == mine


def test_opt_out_leaves_flags_alone(monkeypatch):
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_enable_fast_math=false")
    monkeypatch.setenv("JAXTRAJ_XLA_SMALL_LOOPS", "0")
    assert _xla.configure_small_loops() is False
    assert os.environ["XLA_FLAGS"] == "--xla_cpu_enable_fast_math=false"
    monkeypatch.setenv("JAXTRAJ_XLA_SMALL_LOOPS", "1")
    assert _xla.configure_small_loops() is True
    assert "xla_cpu_small_while_loop_byte_threshold" in os.environ["XLA_FLAGS"]


@pytest.mark.parametrize("opt", ["1", "0"])
def test_filter_and_smoother_scans_compile_to_one_kernel(opt):
    """With the option, the filter's and the RTS smoother's scans are one kernel each;
    without it neither is. (On jaxlib 0.10.2 the smoother's loop stays as thunks when YNN
    fusions are on: its body then holds YNNPACK custom calls; jaxtraj turns them off.)"""
    filter_calls, smoother_calls = _probe({"JAXTRAJ_XLA_SMALL_LOOPS": opt})
    if opt == "0":
        assert (filter_calls, smoother_calls) == (0, 0)
        return
    assert filter_calls == 1
    if _xla._jaxlib_minor() in _xla.YNN_CHECKED:
        assert smoother_calls == 1


def test_ynn_flag_is_appended_and_the_users_choice_wins():
    assert _xla.with_no_ynn_flag("") == "--xla_cpu_experimental_ynn_fusion_type="
    flags = _xla.with_no_ynn_flag("--xla_cpu_enable_fast_math=false")
    assert flags == "--xla_cpu_enable_fast_math=false --xla_cpu_experimental_ynn_fusion_type="
    mine = "--xla_cpu_experimental_ynn_fusion_type=dot"
    assert _xla.with_no_ynn_flag(mine) == mine


def test_ynn_opt_out_unknown_versions_and_user_flags(monkeypatch):
    monkeypatch.setattr(_xla, "_jaxlib_minor", lambda: (0, 10))
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_enable_fast_math=false")
    monkeypatch.setenv("JAXTRAJ_XLA_YNN_FUSIONS", "1")
    assert _xla.configure_no_ynn_fusions() is False
    assert os.environ["XLA_FLAGS"] == "--xla_cpu_enable_fast_math=false"
    monkeypatch.delenv("JAXTRAJ_XLA_YNN_FUSIONS")
    assert _xla.configure_no_ynn_fusions() is True
    assert os.environ["XLA_FLAGS"].endswith(" --xla_cpu_experimental_ynn_fusion_type=")
    # a jaxlib it was not checked on: XLA aborts on an unknown flag, so nothing is added
    monkeypatch.setattr(_xla, "_jaxlib_minor", lambda: (9, 0))
    monkeypatch.setenv("XLA_FLAGS", "")
    assert _xla.configure_no_ynn_fusions() is False
    assert os.environ["XLA_FLAGS"] == ""
    # the user's own value is kept and reported
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_experimental_ynn_fusion_type=dot")
    assert _xla.configure_no_ynn_fusions() is False
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_experimental_ynn_fusion_type= --xla_dump_to=x")
    assert _xla.configure_no_ynn_fusions() is True


_SOLVER_PROBE = """
import jax
jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp
import jaxtraj
from jaxtraj.solve import _reconstruct_points
F, k, n = 30, 5, 16
P = jnp.tile(jnp.eye(3, 4), (F, 1, 1)).at[:, 0, 3].set(jnp.linspace(-1, 1, F))
uv, w = jnp.zeros((n, F, 2)), jnp.ones((n, F))
basis = jaxtraj.dct_basis(jnp.linspace(0, 1, F), k)
hlo = _reconstruct_points.lower(P, uv, basis, w, jnp.asarray(20.0), 1, True, None, 8)
print(hlo.compile().as_text().count("__ynn_fusion"))
"""


def test_the_solver_compiles_without_ynn_fusions():
    if _xla._jaxlib_minor() not in _xla.YNN_CHECKED:
        pytest.skip(f"jaxlib {jaxlib.__version__}: the YNN option is not set on this version")
    env = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}
    env["XLA_FLAGS"] = " ".join(
        f for f in env.get("XLA_FLAGS", "").split() if "ynn_fusion_type" not in f
    )
    out = subprocess.run(
        [sys.executable, "-c", _SOLVER_PROBE], env=env, capture_output=True, text=True,
        timeout=300,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr[-2000:]
    assert int(out.stdout.strip().splitlines()[-1]) == 0
