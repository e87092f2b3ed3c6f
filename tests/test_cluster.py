"""Sharded bakes on Dask: the serial bake's table, bit for bit, however the batches run."""

import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import yaml

from models.bundle_table import BundleTable
from pipeline.stages import bake as bake_stage
from pipeline import cli
from pipeline.stages import fiber as fiber_stage
from pipeline.loading import load_config
from tests.test_cli import ROOT

# an ellipse: 3 incident azimuths x 5 batches, so that batches finish out of order
TINY = {"name": "c", "wavelengths": {"start_nm": 450, "stop_nm": 650, "count": 3},
        "fiber": {"model": "mie", "radius_um": 3.0, "ior": {"k": 1e-3}}, "tabulate": {"theta_i_step_deg": 30},
        "bundle": {"shape": "ellipse", "semi_axes_um": [25.0, 15.0], "seed": 2},
        "bake": {"paths_per_phi_i": 10000, "batch_paths": 2048, "theta_i_step_deg": 30, "phi_i_step_deg": 45,
                 "n_theta_o": 12, "n_phi_o": 24, "checkpoint_every_s": 0.01}}


@pytest.fixture(scope="module")
def serial(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("cluster")
    path = tmp / "c.yaml"
    path.write_text(yaml.safe_dump(TINY))
    cfg = load_config(path)
    fiber_stage.run(cfg, tmp / "serial")
    bake_stage.run(cfg, tmp / "serial")
    return cfg, path, tmp


def _table(root):
    return BundleTable.load(root / "c" / "bake" / "bundle_table.npz")


def _same(a, b):
    return all(np.array_equal(getattr(a, k), getattr(b, k)) for k in ("values", "stderr", "passthrough", "absorbed",
                                                                                      "single"))


def _fiber(serial, root):
    cfg, _, tmp = serial
    (root / "c" / "fiber").mkdir(parents=True)
    for f in (tmp / "serial" / "c" / "fiber").iterdir():
        (root / "c" / "fiber" / f.name).write_bytes(f.read_bytes())


def test_local_cluster_bake_is_the_serial_bake_resumes_and_survives_a_killed_worker(serial, tmp_path, monkeypatch):
    """Interrupted after 4 of 15 batches on the cluster, resumed on it, and one worker
    process killed (SIGKILL) as the resumed bake's first results arrive, with most batches
    still to trace: Dask traces the lost ones again (the nanny restarts the worker), and
    the table is still the serial bake's, bit for bit."""
    from distributed import default_client

    from pipeline import cluster

    cfg, path, tmp = serial
    _fiber(serial, tmp_path)
    bake_stage.run(cfg, tmp_path, stop_after=4, workers=2)
    assert (tmp_path / "c" / "bake" / "checkpoint.npz").exists()

    killed, unpack = [], cluster.unpack

    def unpack_then_kill(packed):
        if not killed:
            pid = sorted(default_client().run(os.getpid).values())[0]
            os.kill(pid, signal.SIGKILL)
            killed.append(pid)
        return unpack(packed)

    monkeypatch.setattr(cluster, "unpack", unpack_then_kill)
    assert cli.main(["--artifacts", str(tmp_path), "bake", str(path), "--workers", "2"]) == 0
    assert killed
    assert _same(_table(tmp_path), _table(tmp / "serial"))


def test_a_real_scheduler_and_two_workers_on_loopback(serial, tmp_path):
    cfg, path, tmp = serial
    _fiber(serial, tmp_path)
    dask = os.path.join(os.path.dirname(sys.executable), "dask")
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    sched_file = tmp_path / "scheduler.json"
    procs = [subprocess.Popen([dask, "scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                               "--scheduler-file", str(sched_file)], env=env, cwd=ROOT,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    try:
        for _ in range(100):
            if sched_file.exists() and sched_file.stat().st_size:
                break
            time.sleep(0.1)
        address = yaml.safe_load(sched_file.read_text())["address"]
        for _ in range(2):
            procs.append(subprocess.Popen([dask, "worker", address, "--nthreads", "1", "--no-dashboard"],
                                          env=env, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        assert cli.main(["--artifacts", str(tmp_path), "bake", str(path), "--scheduler", address]) == 0
        assert _same(_table(tmp_path), _table(tmp / "serial"))
    finally:
        for p in procs[::-1]:
            p.terminate()
        for p in procs:
            p.wait(timeout=30)


def test_an_unreachable_scheduler_is_named_and_nothing_is_written(serial, tmp_path, capsys, monkeypatch):
    from pipeline import cluster

    monkeypatch.setattr(cluster, "CONNECT_TIMEOUT", "2s")
    cfg, path, tmp = serial
    _fiber(serial, tmp_path)
    assert cli.main(["--artifacts", str(tmp_path), "bake", str(path), "--scheduler", "tcp://127.0.0.1:9"]) == 2
    err = capsys.readouterr().err
    assert "tcp://127.0.0.1:9" in err and "Traceback" not in err
    assert not (tmp_path / "c" / "bake" / "bundle_table.npz").exists()


def test_a_worker_with_other_code_refuses_its_tasks():
    from pipeline import cluster
    from pipeline.config import Config

    with pytest.raises(RuntimeError, match="same checkout"):
        cluster.trace_batch(Config.model_validate(TINY).model_dump_json(), None, 0, 0, 1, code="another-checkout")


WARMED_BATCH = """
import ast, json, sys
from pipeline import cluster
from pipeline.artifacts import load_fiber_table
from pipeline.loading import load_config

cfg = load_config(sys.argv[1])
fiber = load_fiber_table(cfg, sys.argv[2])
cluster.warm_up([cfg.bake.variant])
parsed, parse = [], ast.parse
ast.parse = lambda *a, **k: parsed.append(1) or parse(*a, **k)
cluster.trace_batch(cfg.model_dump_json(), fiber, 0, 0, 64, cluster.code_digest(cfg))
print(json.dumps(len(parsed)))
"""


def test_a_warmed_up_worker_traces_a_batch_without_parsing_python_source(serial):
    """CPython 3.11 cannot build ASTs in two threads at once (gh-106905), and a Dask worker's
    event loop parses too: once :func:`pipeline.cluster.warm_up` has run (the worker plugin
    does, before a worker's first task), a batch must parse nothing (a fresh interpreter, so
    that no import is already cached)."""
    cfg, path, tmp = serial
    out = subprocess.run([sys.executable, "-c", WARMED_BATCH, str(path), str(tmp / "serial")], cwd=ROOT,
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split()[-1] == "0", "a warmed-up worker's batch still parsed Python source"
