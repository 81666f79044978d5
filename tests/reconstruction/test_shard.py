"""Sharding the pixel axis: equal results on 1 and 4 devices, helpers, multi-host setup.

The 4-device checks run in a subprocess: the device count must be set (XLA_FLAGS)
before jax is imported, and this test process has imported it already.
"""

import os
import subprocess
import sys
import textwrap

import jax
import jax.random as jr
import numpy as np
import pytest

import evhsi_jax as ev
from evhsi_jax._base._shard import (
    chunk_groups,
    initialize_distributed,
    pixel_mesh,
    sub_batch_for,
)

FOUR_DEVICES = textwrap.dedent(
    """
    import jax, jax.random as jr, numpy as np
    import evhsi_jax as ev
    from evhsi_jax._model._dynamic import dynamic_scene
    from evhsi_jax._base._shard import pixel_mesh

    assert len(jax.devices()) == 4, jax.devices()
    mesh = pixel_mesh()
    rig = ev.Rig()
    scenes = dynamic_scene("mixed", (6, 12), sweeps=2)
    # Simulator: 3 column chunks of 4 over 4 devices (the group padded).
    a = ev.simulate(scenes, rig, sweeps=2, chunk_columns=4, key=jr.key(1))
    b = ev.simulate(scenes, rig, sweeps=2, chunk_columns=4, key=jr.key(1), mesh=mesh)
    for k in ("x", "y", "p", "t_us"):
        assert np.array_equal(getattr(a, k), getattr(b, k)), k
    # Reconstruction: several CPU devices solve one pixel per step (sub_batch_for).
    # Each pixel's arithmetic is the same, but XLA compiles the multi-device kernel
    # differently (not the chunk size: the plain run is bit-identical for chunks of
    # 4/16/64; not Eigen threading), so allow float32 rounding (observed: 3.2e-5 on
    # reflectance ~0.5).
    kw = dict(chunk_pixels=16, sub_batch=1, return_info=True)
    one, i1 = ev.reconstruct(a, rig, **kw)
    four, i4 = ev.reconstruct(a, rig, mesh=mesh, **kw)
    np.testing.assert_allclose(four, one, rtol=0, atol=2e-4)
    assert np.array_equal(i1.solved, i4.solved) and np.array_equal(i1.events, i4.events)
    np.testing.assert_allclose(i4.kkt, i1.kkt, rtol=0, atol=1e-5)
    print("OK", len(a), float(np.abs(one - four).max()))
    """
)


@pytest.mark.slow  # ~1 min; the two-process run of test_reliability covers several devices
def test_four_cpu_devices_equal_one():
    env = dict(os.environ)
    flags = [
        f for f in env.get("XLA_FLAGS", "").split()
        if "xla_force_host_platform_device_count" not in f  # conftest's 1 goes
    ]  # fmt: skip
    env["XLA_FLAGS"] = " ".join([*flags, "--xla_force_host_platform_device_count=4"])
    env["JAX_PLATFORMS"] = "cpu"
    proc = subprocess.run(
        [sys.executable, "-c", FOUR_DEVICES],
        env=env,
        capture_output=True,
        text=True,
        timeout=400,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.startswith("OK")


def test_one_device_mesh_equals_the_plain_run():
    rig = ev.Rig()
    scene = ev.load_scene("colorchecker", (4, 6))
    events = ev.simulate(scene, rig, key=jr.key(0))
    mesh = pixel_mesh(1)
    kw = dict(chunk_pixels=16, sub_batch=8)
    assert np.array_equal(
        ev.reconstruct(events, rig, **kw), ev.reconstruct(events, rig, mesh=mesh, **kw)
    )
    sim = ev.simulate(scene, rig, key=jr.key(0), mesh=mesh)
    assert np.array_equal(sim.t_us, events.t_us)


def test_helpers():
    assert chunk_groups(5, None) == [[0], [1], [2], [3], [4]]
    mesh = pixel_mesh(1)
    assert mesh.axis_names == ("pixels",) and mesh.devices.size == 1
    assert sub_batch_for(mesh, 128) == 128  # one device: batches are safe
    with pytest.raises(ValueError, match="devices"):
        pixel_mesh(len(jax.devices()) + 1)


def test_distributed_settings_are_validated(monkeypatch):
    monkeypatch.setenv("EVHSI_NUM_PROCESSES", "two")
    monkeypatch.setattr(jax.distributed, "is_initialized", lambda: False)
    with pytest.raises(ValueError, match="EVHSI_NUM_PROCESSES"):
        initialize_distributed()


def test_distributed_passes_settings_to_jax(monkeypatch):
    """The settings reach jax.distributed.initialize (the real two-process run is in
    tests/test_reliability.py)."""
    seen = {}
    monkeypatch.setattr(jax.distributed, "is_initialized", lambda: False)
    monkeypatch.setattr(jax.distributed, "initialize", lambda **kw: seen.update(kw))
    monkeypatch.setenv("EVHSI_COORDINATOR", "host0:1234")
    monkeypatch.setenv("EVHSI_NUM_PROCESSES", "2")
    monkeypatch.setenv("EVHSI_PROCESS_ID", "0")  # the coordinator: no port to probe
    monkeypatch.setenv("EVHSI_DISTRIBUTED_TIMEOUT", "7")
    initialize_distributed()
    assert seen == dict(
        coordinator_address="host0:1234",
        num_processes=2,
        process_id=0,
        initialization_timeout=37,  # ours (7 s) fires first
    )
    monkeypatch.setenv("EVHSI_DISTRIBUTED_TIMEOUT", "soon")
    with pytest.raises(ValueError, match="EVHSI_DISTRIBUTED_TIMEOUT"):
        initialize_distributed()


def test_cli_devices_asks_xla_for_host_devices(monkeypatch):
    from evhsi_jax.cli import _cpu_devices

    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_enable_fast_math=false")
    _cpu_devices(1)
    assert os.environ["XLA_FLAGS"] == "--xla_cpu_enable_fast_math=false"
    _cpu_devices(2)
    assert os.environ["XLA_FLAGS"].endswith("--xla_force_host_platform_device_count=2")
    _cpu_devices(4)  # a count already there wins
    assert "count=4" not in os.environ["XLA_FLAGS"]
    monkeypatch.setenv("XLA_FLAGS", "")
    monkeypatch.setattr(os, "sched_getaffinity", lambda _: {0, 1, 2}, raising=False)
    _cpu_devices(None)  # the default: one host device per usable core
    assert os.environ["XLA_FLAGS"] == "--xla_force_host_platform_device_count=3"
