"""volpath_delta's ``shadow_prediction`` (issue 29), measured before it was removed: a
Russian roulette before each shadow ray from a homogeneous medium, on the transmittance
predicted from the path's last shadow ray (its first piece's optical depth, less
sigma_t times the distance moved since). Per tuning-half sphere: the mean, relative
variance of a 32-spp render over 16 seeds, median time, and efficiency over the
setting 0 (off).

    python3 benchmarks/refactor/shadow_prediction.py 0,0.05,0.2 tuning04_sphere_spot ...
"""
import sys, time, tempfile, statistics
from pathlib import Path
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import mitsuba_plugins
import mitsuba as mi, drjit as dr, numpy as np
import dense_heldout as dh
cases = {c.name: c for c in dh.family()}
tmp = Path(tempfile.mkdtemp())
qs=[float(x) for x in sys.argv[1].split(",")]
for name in sys.argv[2:]:
    sc = dh.scene(cases[name], 32, tmp)
    out=[]
    for q in qs:
        integ = mi.load_dict({"type": "volpath_delta", "shadow_prediction": q})
        mi.render(sc, integrator=integ, spp=32, seed=10**6); dr.sync_thread()
        ts=[]; imgs=[]
        for s in range(16):
            t0=time.perf_counter(); img=mi.render(sc, integrator=integ, spp=32, seed=s); dr.eval(img); dr.sync_thread()
            ts.append(time.perf_counter()-t0); imgs.append(np.array(img))
        a=np.array(imgs); m=a.mean(0); rv=float(np.mean(a.var(0,ddof=1)/(m**2+1e-2))); t=statistics.median(ts)
        out.append((q, a.mean(), rv, t, 1/(rv*t)))
    base=out[0][4]
    for q,mean,rv,t,e in out:
        print(f"{name} q_min {q:g}: mean {mean:.5f} relvar {rv:.4g} time {t*1e3:.1f} ms eff ratio {e/base:.3f}", flush=True)
