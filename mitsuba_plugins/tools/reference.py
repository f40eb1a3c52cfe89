"""High-spp references as Dask tasks: one pass = one task, on this machine or a cluster.

``reference(scene, integrator, spp, passes, ...)`` renders ``spp`` samples per pixel as
``passes`` passes whose seeds are fixed by the pass index (``seed + k``), each pass a
task of Dask's ``distributed`` scheduler, and writes into the output folder:

* ``mean.exr``: the mean of the passes; ``stderr.exr``: its standard error (the
  passes' standard deviation / sqrt(passes));
* ``reference.json``: the settings and, per pass, its ``seed``, ``worker`` and
  ``seconds`` (the render, compilation included on a worker's first pass);
* ``passes/pass_KKKKK.npz``: each finished pass, written atomically as it arrives.

Where it runs does not change the image: the same seeds give the same passes on 1
worker, W workers or a remote cluster (up to the order in which the film adds a pixel's
samples, ~1e-7 relative). Faults: a worker that dies mid-pass loses nothing, Dask runs
the task again and the seed makes the retry identical; an interrupted run leaves no
``mean.exr`` (the final files are written to a temporary name and renamed), and its
finished passes are kept, so a re-run with the same settings renders only the rest.

Without ``scheduler`` an embedded ``LocalCluster`` of ``workers`` processes is started
(default :data:`DEFAULT_WORKERS`), each rendering with ``cores / workers`` Dr.Jit
threads so the workers do not oversubscribe the cores. With ``scheduler`` (``tcp://host:8786``) the
passes go to an existing cluster; the scene's files must then be readable at the same
path on every worker (they are not shipped).
"""
from __future__ import annotations

import hashlib
import json
import os
import threading
import time
from pathlib import Path

import numpy as np

from mitsuba_plugins import output

#: seconds to wait for an existing scheduler before giving up
CONNECT_TIMEOUT = 5.0
#: times Dask runs a pass again after an error in it (a dead worker is not an error:
#: its tasks are rescheduled by the scheduler anyway)
RETRIES = 2
#: local worker processes by default: one, rendering with every core's Dr.Jit thread.
#: On the 2-core benchmark machine it finished a 38 s reference in 38 s where two
#: one-thread workers took 45 s (benchmarks/results/reference_scaling.md): Dr.Jit
#: already spreads a pass over the cores, and two processes contend for them.
DEFAULT_WORKERS = 1
#: pass files of this format are reused on a re-run
PASS_FORMAT = 1

#: per worker process: (scene path, res, digest) -> scene; (that, integrator) -> integrator
_SCENES: dict = {}
_INTEGRATORS: dict = {}
#: local clusters started here and not closed yet (closed on an interrupt)
_CLUSTERS: list = []
_CLUSTERS_LOCK = threading.Lock()


class ReferenceError(RuntimeError):
    """A reference cannot be rendered as asked (one line, for the CLI)."""


def render_pass(scene_path: str, res, integrator: dict, spp: int, seed: int, variant: str,
                threads, digest: str) -> dict:
    """One pass, run in a Dask worker: ``{"image", "seed", "seconds", "invalid",
    "worker"}``. The scene and integrator are loaded once per worker process (the kernel
    compiles on a worker's first pass only)."""
    import mitsuba_plugins  # noqa: F401  -- chooses libLLVM before Dr.Jit loads
    import drjit as dr
    import mitsuba as mi
    if threads:
        dr.set_thread_count(int(threads))
    if mi.variant() != variant:
        mi.set_variant(variant)   # registers the plugins in the worker process
    from mitsuba_plugins.tools.scenes import load_scene
    from mitsuba_plugins.tools.stats import timed_pass
    from mitsuba_plugins.validity import counted
    key = (variant, str(scene_path), res, digest)
    if key not in _SCENES:
        _SCENES.clear()
        _INTEGRATORS.clear()
        _SCENES[key] = load_scene(scene_path, res)
    ikey = json.dumps(integrator, sort_keys=True)
    if ikey not in _INTEGRATORS:
        _INTEGRATORS[ikey] = counted(mi.load_dict(integrator))
    seconds, image, invalid = timed_pass(_SCENES[key], _INTEGRATORS[ikey], spp, seed)
    return {"image": image, "seed": seed, "seconds": seconds, "invalid": invalid,
            "worker": _worker_name()}


def _worker_name() -> str:
    try:
        from distributed import get_worker
        worker = get_worker()
        return str(worker.name if worker.name is not None else worker.address)
    except (ImportError, ValueError):
        return f"pid {os.getpid()}"


def _settings(scene_path, res, integrator, spp_per_pass, seed, variant) -> dict:
    from mitsuba_plugins.tools.scenes import scene_digest
    return {"scene": str(Path(scene_path).resolve()), "scene_digest": scene_digest(scene_path),
            "res": res, "integrator": integrator, "spp_per_pass": spp_per_pass,
            "seed": seed, "variant": variant}


def _settings_key(settings: dict) -> str:
    return hashlib.sha256(json.dumps(settings, sort_keys=True).encode()).hexdigest()


def _pass_file(folder: Path, k: int) -> Path:
    return folder / "passes" / f"pass_{k:05d}.npz"


def _load_pass(path: Path, key: str, shape) -> dict | None:
    """A finished pass of these settings, or None (missing, other settings, damaged)."""
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as f:
            info = json.loads(str(f["info"]))
            image = np.array(f["image"])
    except Exception:   # a damaged file is rendered again, never averaged in
        return None
    if info.get("key") != key or info.get("format") != PASS_FORMAT or \
            (shape is not None and image.shape != shape) or not np.all(np.isfinite(image)):
        return None
    return {**info, "image": image}


def _save_pass(path: Path, key: str, result: dict) -> None:
    info = {k: v for k, v in result.items() if k != "image"}
    info.update(key=key, format=PASS_FORMAT)
    with output.atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, image=result["image"], info=json.dumps(info))


def connect(workers: int | None = None, scheduler: str | None = None, quiet: bool = True):
    """``(client, threads)``: a client of the cluster at ``scheduler``, or of a new
    ``LocalCluster`` of ``workers`` processes (closed with the client); ``threads``: the
    Dr.Jit thread count each local worker renders with (None on a remote cluster)."""
    import logging

    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise ReferenceError("Dask's 'distributed' is not installed: pip install "
                             "'mitsuba-plugins[distributed]' (or pip install distributed)") from None
    if scheduler:
        check_scheduler(scheduler)
        return _client(scheduler, Client), None
    cores = os.cpu_count() or 1
    workers = workers or DEFAULT_WORKERS
    if workers > cores:
        raise ReferenceError(f"--workers = {workers} is invalid; allowed: an integer in "
                             f"[1, {cores}] (the cores of this machine)")
    threads = max(1, cores // workers)
    cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                           dashboard_address=":0",
                           silence_logs=logging.ERROR if quiet else logging.WARNING)
    _CLUSTERS.append(cluster)
    client = Client(cluster)
    client._mitsuba_plugins_cluster = cluster   # closed by close()
    return client, threads


#: address schemes --scheduler accepts (Dask's others need set-up this tool does not do:
#: certificates for tls://, UCX for ucx://)
SCHEMES = ("tcp",)


def check_scheduler(address: str) -> None:
    """Refuse an address that is empty or of a scheme other than tcp://, in one line."""
    scheme, sep, rest = address.partition("://")
    if not sep:
        scheme, rest = "tcp", address
    host, _, port = rest.rpartition(":")
    if scheme not in SCHEMES or not host or not port.isdigit():
        raise ReferenceError(f"--scheduler = {address!r} is invalid; allowed: a Dask "
                             "scheduler's address tcp://HOST:PORT (or HOST:PORT)")


def _reason(error: BaseException) -> str:
    text = str(error).strip()
    return text.splitlines()[0] if text else type(error).__name__


def _client(scheduler: str, Client):
    """A client of the scheduler at ``scheduler``, or one line within about
    :data:`CONNECT_TIMEOUT` seconds: Dask's handshake is tried first with a deadline
    (``Client(timeout=...)`` alone waited for ever on a port that accepts and never
    answers), then the client is made in a thread that is given up after the same time."""
    import asyncio
    import threading
    from distributed.comm import connect as comm_connect

    def fail(reason):
        raise ReferenceError(f"--scheduler '{scheduler}': no Dask scheduler answered within "
                             f"{CONNECT_TIMEOUT:g} s ({reason})") from None

    async def handshake():
        comm = await comm_connect(scheduler, timeout=CONNECT_TIMEOUT)
        await comm.close()
    try:
        asyncio.run(asyncio.wait_for(handshake(), CONNECT_TIMEOUT))
    except asyncio.TimeoutError:
        fail("no handshake")
    except (OSError, TimeoutError, ValueError, TypeError, RuntimeError) as error:
        fail(_reason(error))
    made = {}

    def make():
        try:
            made["client"] = Client(scheduler, timeout=f"{CONNECT_TIMEOUT}s")
        except Exception as error:   # handed to the caller as one line
            made["error"] = error
    thread = threading.Thread(target=make, daemon=True, name="dask-connect")
    thread.start()
    thread.join(2 * CONNECT_TIMEOUT)
    if "client" in made:
        return made["client"]
    fail(_reason(made["error"]) if "error" in made else "the client did not register")


def close(client) -> None:
    cluster = getattr(client, "_mitsuba_plugins_cluster", None)
    client.close()
    if cluster is not None:
        cluster.close()
        _forget(cluster)


def _forget(cluster) -> None:
    """Drop a closed cluster from :data:`_CLUSTERS`, once: an interrupt's
    :func:`shutdown` and the rendering thread's :func:`close` may both get there (that
    race once made an interrupted ``reference`` exit 1 with ValueError, not 130)."""
    with _CLUSTERS_LOCK:
        if cluster in _CLUSTERS:
            _CLUSTERS.remove(cluster)


def shutdown() -> None:
    """Stop the worker processes of local clusters still running (on an interrupt)."""
    for cluster in list(_CLUSTERS):
        try:
            cluster.close(timeout=5)
        except Exception:   # already going down
            pass
        _forget(cluster)


def reference(scene_path: str, integrator: dict, spp: int, passes: int, out_dir,
              res: int | None = None, seed: int = 0, workers: int | None = None,
              scheduler: str | None = None, client=None, threads: int | None = None,
              variant: str | None = None, progress: bool = True) -> dict:
    """Render and write a reference (see the module docstring); returns what
    ``reference.json`` holds. ``client``: an existing Dask client to use (else one is
    made from ``workers`` / ``scheduler`` and closed at the end). ``threads``: Dr.Jit
    threads per worker (default: cores / workers on a local cluster, Dr.Jit's own
    default, all cores, on a remote one)."""
    from mitsuba_plugins.registry import default_variant
    if passes < 1 or spp < passes or spp % passes:
        raise ReferenceError(f"--spp {spp} must be a positive multiple of --passes {passes}")
    if not Path(scene_path).is_file():
        raise ReferenceError(f"scene file not found: {scene_path}")
    out = Path(out_dir)
    output.check_folder_target(out, option="--output")
    output.check_targets([out / "mean.exr", out / "stderr.exr", out / "reference.json",
                          _pass_file(out, 0)], option="--output")
    variant = variant or default_variant()
    settings = _settings(scene_path, res, integrator, spp // passes, seed, variant)
    key = _settings_key(settings)

    results, shape = {}, None
    for k in range(passes):
        done = _load_pass(_pass_file(out, k), key, shape)
        if done is not None:
            results[k] = done
            shape = done["image"].shape
    todo = [k for k in range(passes) if k not in results]
    t0 = time.perf_counter()
    if todo:
        own = client is None
        if own:
            client, local_threads = connect(workers, scheduler)
            threads = threads or local_threads
        def store(k, result):
            _save_pass(_pass_file(out, k), key, result)
            results[k] = result
        try:
            run_passes(client, threads, settings, todo, store, passes, progress)
        finally:
            if own:
                close(client)
    return _finish(out, settings, results, passes, time.perf_counter() - t0,
                   resumed=passes - len(todo))


def run_passes(client, threads, settings: dict, todo, store, total: int,
               progress: bool = True) -> None:
    """Render passes ``todo`` (pass ``k`` with seed ``settings["seed"] + k``) as tasks on
    ``client``'s cluster; ``store(k, result)`` is called as each arrives. An interrupt
    (or an error) cancels the passes still queued."""
    from distributed import as_completed
    key = _settings_key(settings)
    n_workers = len(client.scheduler_info().get("workers", {}))
    futures = [client.submit(render_pass, settings["scene"], settings["res"],
                             settings["integrator"], settings["spp_per_pass"],
                             (settings["seed"] + k) % 2 ** 32, settings["variant"], threads,
                             settings["scene_digest"], key=f"mitsuba-pass-{key[:16]}-{k}",
                             retries=RETRIES, pure=False)
               for k in todo]
    index = {f.key: k for f, k in zip(futures, todo)}
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=total, initial=total - len(todo), unit="pass", leave=False,
                   desc=f"reference {settings['integrator']['type']} ({n_workers} workers)")
    try:
        for future in as_completed(futures):
            store(index[future.key], future.result())
            if bar is not None:
                bar.update(1)
    finally:
        if bar is not None:
            bar.close()
        for future in futures:
            future.cancel()


def estimate_on_cluster(scene_path: str, res, integrator: dict, spp_per_pass: int, passes: int,
                        seed: int, scheduler: str | None = None, workers: int | None = None,
                        progress: bool = True):
    """``passes`` passes rendered as tasks (on the cluster at ``scheduler``, else a local
    one), as a :class:`~mitsuba_plugins.tools.stats.Estimate`: the same seeds as
    :func:`~mitsuba_plugins.tools.stats.render_passes` with ``seed`` (``compare``'s
    reference cache uses it)."""
    import mitsuba as mi
    from mitsuba_plugins.tools.stats import Estimate
    settings = _settings(scene_path, res, integrator, spp_per_pass, seed, mi.variant())
    results = {}
    client, threads = connect(workers, scheduler)
    try:
        run_passes(client, threads, settings, range(passes), results.__setitem__, passes,
                   progress)
    finally:
        close(client)
    ordered = [results[k] for k in range(passes)]
    return Estimate.from_passes([r["image"] for r in ordered], spp_per_pass,
                                [r["seconds"] for r in ordered],
                                sum(r["invalid"] for r in ordered))


def _finish(out: Path, settings: dict, results: dict, passes: int, wall: float,
            resumed: int) -> dict:
    from mitsuba_plugins.tools.stats import Estimate
    images = [results[k]["image"] for k in range(passes)]
    est = Estimate.from_passes(images, settings["spp_per_pass"])
    se = est.se if passes > 1 else np.zeros_like(est.mean)
    info = {
        **{k: v for k, v in settings.items()},
        "spp": settings["spp_per_pass"] * passes,
        "passes": passes,
        "resumed_passes": resumed,
        "wall_seconds": wall,
        "invalid": int(sum(results[k]["invalid"] for k in range(passes))),
        "per_pass": [{"pass": k, "seed": int(results[k]["seed"]),
                      "worker": results[k]["worker"], "seconds": float(results[k]["seconds"]),
                      "invalid": int(results[k]["invalid"])} for k in range(passes)],
    }
    output.write_exr(out / "stderr.exr", se)
    output.write_json(out / "reference.json", info, indent=1)
    output.write_exr(out / "mean.exr", est.mean)   # last: its presence means complete
    return info
