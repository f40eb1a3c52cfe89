"""Adjoint-driven Russian roulette (``mitsuba_plugins.adjoint``, issue 29) against the
throughput roulette on one scene of ``dense_heldout.py``: a 16-spp pilot learns the
adjoint grid, then each configuration (grid resolution, q_min, omega) renders 48 spp,
6 timed renders, relMSE against a 2048-spp reference. ``python3
benchmarks/refactor/adjoint_rr.py tuning12_sphere_area``."""
import sys, time, tempfile
from pathlib import Path
sys.path.insert(0, "/work/main/benchmarks")
import dense_heldout as dh, dense
from common import timed_render
import mitsuba as mi, numpy as np, drjit as dr
from mitsuba_plugins.tools import stats
from mitsuba_plugins import adjoint as A
name = sys.argv[1]
case = [c for c in dh.family() if c.name == name][0]
print(case)
tmp = Path(tempfile.mkdtemp())
sc = dh.scene(case, 32, tmp)
ref = dense.reference(sc, 2048)
integ = mi.load_dict({"type": "volpath_delta"})
SPP = 48
def measure(label, n=6):
    timed_render(sc, integ, SPP, 0)
    ts, es, en = [], [], []
    for s in range(n):
        t, img = timed_render(sc, integ, SPP, 100 + s)
        ts.append(t); es.append(stats.rel_mse(img, ref)); en.append(img.sum() / ref.sum())
    t, e = np.median(ts), np.mean(es)
    print(f"{label:28s} {t*1e3:6.1f} ms relMSE {e:.4g} eff {1/(t*e):8.1f} energy {np.mean(en):.4f}", flush=True)
measure("plain")
for res in (4, 8, 16):
    l = A.Learner(A.AdjointGrid(A.media_bounds(sc), res)); integ.adjoint = l
    mi.render(sc, integrator=integ, spp=16, seed=12345); 
    for qmin in (0.25, 0.5):
        for om in (0.03, 0.1, 0.3):
            integ.adjoint = l.guide(om, qmin)
            measure(f"res {res} qmin {qmin} omega {om}")
