"""Time per sample of ``volpath_delta`` (defaults) over ``volpath``'s on scenes of
``benchmarks/dense.py``'s family, for a checkout given as its folder: 32x32, 16 spp, two
warm-up renders each, then 9 renders alternating, median over median; prints
``case ratio`` pairs on one line.

For an old commit, check it out into a worktree and copy it into one importable package
as ``ab.py`` says (``integrators/`` and ``media/`` under ``mitsuba_plugins/``), then from a
folder with neither checkout on the path::

    cd /tmp && PYTHONPATH=/tmp/oldpkg python3 /work/main/benchmarks/refactor/dense_time_per_sample.py /tmp/old plume_env,plume_area

It imports that checkout's ``benchmarks/dense.py`` for the scenes, so it also works as a
``git bisect run`` probe (issue 29 used it to find which commit slowed plume_env).
"""
import statistics
import sys
import tempfile
import time
from pathlib import Path

checkout = sys.argv[1]
sys.path.insert(0, f"{checkout}/benchmarks")
import mitsuba_plugins  # noqa: E402,F401  -- chooses libLLVM before drjit loads
import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

mi.set_variant("llvm_ad_rgb")
import dense  # noqa: E402

out = []
for name in sys.argv[2].split(","):
    case = next(c for c in dense.FAMILY if c.name == name)
    scene = dense.scene(case, 32, Path(tempfile.mkdtemp()))
    integ = {"volpath": mi.load_dict({"type": "volpath"}),
             "ours": mi.load_dict({"type": "volpath_delta"})}

    def seconds(key, seed):
        t0 = time.perf_counter()
        dr.eval(mi.render(scene, integrator=integ[key], spp=16, seed=seed))
        dr.sync_thread()
        return time.perf_counter() - t0

    for key in integ:
        seconds(key, 999), seconds(key, 998)
    times = {key: [] for key in integ}
    for run in range(9):
        for key in (list(integ) if run % 2 == 0 else list(integ)[::-1]):
            times[key].append(seconds(key, run))
    out.append(f"{name} {statistics.median(times['ours']) / statistics.median(times['volpath']):.3f}")
print(" ".join(out))
