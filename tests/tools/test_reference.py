"""References as Dask tasks (mitsuba_plugins.tools.reference), on 127.0.0.1 only: the
image does not depend on where the passes ran, a killed worker loses nothing, an
interrupted run leaves no mean.exr and resumes, a bad scheduler fails in one line."""
from __future__ import annotations

import json
import os
import signal
import threading
import time

import mitsuba as mi
import numpy as np
import pytest

from conftest import VARIANT
from helpers import SCENES, assert_same_render, load, render, start_cli
from mitsuba_plugins.tools import reference as ref
from mitsuba_plugins.tools.stats import Estimate

SCENE = str(SCENES / "cornell_box.xml")
INTEGRATOR = {"type": "path_rr", "max_depth": 4}


def _read_exr(path) -> np.ndarray:
    """(H, W, C): a one-channel (mono) EXR reads back as (H, W)."""
    image = np.array(mi.Bitmap(str(path)), dtype=np.float64)
    return image[..., None] if image.ndim == 2 else image


def _single_process(res, spp_per_pass, passes, seed=0) -> Estimate:
    """The same passes rendered here, one after the other."""
    scene = load("cornell_box", res=res)
    images = [render(scene, INTEGRATOR, spp=spp_per_pass, seed=seed + k) for k in range(passes)]
    return Estimate.from_passes(images, spp_per_pass)


@pytest.fixture(scope="module")
def client():
    client, threads = ref.connect(workers=2)
    yield client
    ref.close(client)


def test_mean_equals_single_process_and_uses_both_workers(client, tmp_path):
    info = ref.reference(SCENE, INTEGRATOR, spp=8 * 8, passes=8, out_dir=tmp_path, res=16,
                         client=client, variant=VARIANT, progress=False)
    here = _single_process(16, 8, 8)
    assert_same_render(_read_exr(tmp_path / "mean.exr"), here.mean)
    assert_same_render(_read_exr(tmp_path / "stderr.exr"), here.se)
    saved = json.loads((tmp_path / "reference.json").read_text())
    assert [p["seed"] for p in saved["per_pass"]] == list(range(8))
    assert len({p["worker"] for p in saved["per_pass"]}) == 2, saved["per_pass"]
    assert saved["spp"] == 64 and saved["invalid"] == 0 and info["passes"] == 8


def test_a_killed_worker_loses_no_pass(tmp_path):
    """SIGKILL one of two workers once the first pass has landed: Dask reruns its task
    elsewhere (or on the restarted worker) and the image is the one of the same seeds."""
    client, _ = ref.connect(workers=2)
    try:
        pids = list(client.run(os.getpid).values())
        errors = []

        def run():
            try:
                ref.reference(SCENE, INTEGRATOR, spp=12 * 64, passes=12, out_dir=tmp_path,
                              res=32, client=client, variant=VARIANT, progress=False)
            except BaseException as error:  # reported below
                errors.append(error)
        thread = threading.Thread(target=run)
        thread.start()
        deadline = time.time() + 120
        while not list((tmp_path / "passes").glob("pass_*.npz")) and time.time() < deadline:
            time.sleep(0.05)
        os.kill(pids[0], signal.SIGKILL)
        thread.join(300)
        assert not thread.is_alive() and not errors, errors
    finally:
        ref.close(client)
    here = _single_process(32, 64, 12)
    assert_same_render(_read_exr(tmp_path / "mean.exr"), here.mean)


def test_interrupted_run_leaves_no_mean_and_resumes(tmp_path):
    out = tmp_path / "ref"
    args = ["reference", SCENE, "-i", "path_rr:max_depth=4", "--spp", 16 * 96, "--passes", 16,
            "--res", 32, "--workers", 1, "-q", "-o", out]
    proc = start_cli(*args)
    deadline = time.time() + 120
    while len(list((out / "passes").glob("pass_*.npz"))) < 2 and time.time() < deadline:
        assert proc.poll() is None, proc.communicate()
        time.sleep(0.05)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130 and "interrupted" in err, err
    kept = len(list((out / "passes").glob("pass_*.npz")))
    assert kept >= 2 and not (out / "mean.exr").exists()
    assert not list(out.glob(".*.tmp*"))           # no temporary file left behind

    proc = start_cli(*args)
    stdout, err = proc.communicate(timeout=300)
    assert proc.returncode == 0, err
    saved = json.loads((out / "reference.json").read_text())
    assert saved["resumed_passes"] >= kept - 1    # a pass written at the interrupt may be torn
    here = _single_process(32, 96, 16)
    assert_same_render(_read_exr(out / "mean.exr"), here.mean)


def test_shutdown_and_close_may_both_forget_a_cluster(monkeypatch):
    """An interrupt's shutdown() and the rendering thread's close() can race to drop the
    same local cluster; whichever comes second must not raise (it did: ValueError, exit 1
    instead of 130 in test_interrupted_run_leaves_no_mean_and_resumes)."""
    class Closable:
        closed = 0

        def close(self, timeout=None):
            self.closed += 1

    cluster, client = Closable(), Closable()
    client._mitsuba_plugins_cluster = cluster
    # only this stand-in: shutdown() closes every listed cluster (the module's fixture too)
    monkeypatch.setattr(ref, "_CLUSTERS", [cluster])
    ref.shutdown()
    ref.close(client)                  # second: nothing left to drop, no error
    assert ref._CLUSTERS == [] and cluster.closed == 2 and client.closed == 1


def test_bad_scheduler_fails_in_one_line(tmp_path):
    t0 = time.time()
    proc = start_cli("reference", SCENE, "-i", "path_rr", "--spp", 4, "--passes", 2, "--res", 8,
                "--scheduler", "tcp://127.0.0.1:9", "-o", tmp_path / "r")
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 2, err
    assert err.count("\n") == 1 and "tcp://127.0.0.1:9" in err and "scheduler" in err, err
    assert time.time() - t0 < 20
    assert not (tmp_path / "r" / "mean.exr").exists()


@pytest.fixture
def silent_port():
    """A TCP port on 127.0.0.1 that accepts connections and never answers."""
    import socket
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(8)
    accepted = []
    stop = threading.Event()

    def serve():
        server.settimeout(0.2)
        while not stop.is_set():
            try:
                accepted.append(server.accept()[0])
            except OSError:
                pass
    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    yield server.getsockname()[1]
    stop.set()
    thread.join()
    for conn in accepted:
        conn.close()
    server.close()


def test_a_scheduler_that_never_answers_fails_within_seconds(tmp_path, silent_port):
    """A port that accepts and stays silent (Dask's client once waited there for ever)."""
    t0 = time.time()
    proc = start_cli("reference", SCENE, "-i", "path_rr", "--spp", 4, "--passes", 2, "--res", 8,
                     "--scheduler", f"tcp://127.0.0.1:{silent_port}", "-o", tmp_path / "r")
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 2 and err.count("\n") == 1, err
    assert "no Dask scheduler answered within 5 s" in err
    assert time.time() - t0 < 40


@pytest.mark.parametrize("option, value, message", [
    ("--scheduler", "", "--scheduler = '' is invalid; allowed: a Dask scheduler's address"),
    ("--scheduler", "tls://127.0.0.1:8786", "allowed: a Dask scheduler's address tcp://"),
    ("--scheduler", "ucx://127.0.0.1:8786", "allowed: a Dask scheduler's address tcp://"),
    ("--workers", "1000", "--workers = 1000 is invalid; allowed: an integer in [1, "),
    ("-i", "path_rr:max_depth=-7", "path_rr: parameter 'max_depth' = -7 is invalid"),
])
def test_bad_reference_options_fail_in_one_line_before_any_worker(tmp_path, option, value,
                                                                  message):
    args = ["reference", SCENE, "--spp", 4, "--passes", 2, "--res", 8, "-o", tmp_path / "r"]
    if option != "-i":
        args += ["-i", "path_rr"]
    proc = start_cli(*args, option, value)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 2 and err.count("\n") == 1 and message in err, err
    assert not (tmp_path / "r").exists()


def test_options_are_checked_before_any_work(tmp_path):
    proc = start_cli("reference", SCENE, "-i", "path_rr", "--spp", 10, "--passes", 4,
                "-o", tmp_path / "r")
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 2 and "--spp = 10" in err and "multiple of --passes" in err


def test_compare_renders_missing_references_on_the_cluster(client, tmp_path):
    """compare --scheduler: the cached reference is the one a local render would cache
    (same passes, same seeds), rendered as tasks."""
    from mitsuba_plugins.tools.compare import REFERENCE_PASSES, cached_reference
    scene = load("cornell_box", res=8)
    spec = {"type": "path", "max_depth": 3}
    address = client.scheduler.address
    remote = cached_reference(scene, SCENE, 8, spec, 4 * REFERENCE_PASSES, tmp_path / "a",
                              progress=False, scheduler=address)
    local = cached_reference(scene, SCENE, 8, spec, 4 * REFERENCE_PASSES, tmp_path / "b",
                             progress=False)
    assert_same_render(remote.mean, local.mean)
    assert_same_render(remote.se, local.se)
    assert remote.passes == local.passes == REFERENCE_PASSES
