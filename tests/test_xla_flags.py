"""The XLA:CPU small-loop option set at import: flag handling, and that the filter's scan
really is compiled into one kernel with it (and not without it)."""

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
    """With the option, the filter's scan is one kernel; so is the RTS smoother's on
    jaxlib < 0.10 (jaxlib 0.10.2's XLA leaves that loop as thunks, measured: the option
    then speeds up the filter only). Without the option neither is."""
    filter_calls, smoother_calls = _probe({"JAXTRAJ_XLA_SMALL_LOOPS": opt})
    if opt == "0":
        assert (filter_calls, smoother_calls) == (0, 0)
        return
    assert filter_calls == 1
    old_xla = tuple(int(v) for v in jaxlib.__version__.split(".")[:2]) < (0, 10)
    assert smoother_calls == (1 if old_xla else 0)
