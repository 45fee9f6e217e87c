"""Quick in-process ablation of the ΔM second-difference weight (numpy backend)."""
import json, math, os, sys, tempfile
from concurrent.futures import ProcessPoolExecutor
import numpy as np
sys.path.insert(0, "/work/main")
os.environ["RHONN_BACKEND"] = os.environ.get("RHONN_BACKEND", "numpy")
from harness.paper.benchmark import controller_config_text
from harness.run.inprocess_loop import run_in_process
from harness.analysis.adaptation import adaptation_kpis

CASES = {
    "main": ("dlc-paper", None, 65.0, {}),
    "dlc02": ("dlc-paper", 0.2, 65.0, {}),
    "iso05": ("iso3888-2-low-mu", 0.5, 60.0, {}),
    "swd1": ("sine-with-dwell", 1.0, None, {"amplitude_deg": 270.0, "direction": "left"}),
    "c042": ("mu-step-corner", 1.0, None, {"steps": [[6.0, 0.42]]}),
    "c05": ("mu-step-corner", 1.0, None, {"steps": [[6.0, 0.5]]}),
    "c036": ("mu-step-corner", 1.0, None, {"steps": [[6.0, 0.36]]}),
}
VARIANTS = json.loads(os.environ["VARIANTS"])

def one(job):
    case, vname, seed = job
    sc, mu, v, params = CASES[case]
    text = controller_config_text(seed, VARIANTS[vname])
    with tempfile.NamedTemporaryFile("w", suffix=".toml", delete=False) as f:
        f.write(text)
    ctrl = os.environ.get("CTRL", "nmpc-rhonn")
    r = run_in_process(sc, ctrl if vname != "lmpc" else "lmpc", mu=mu, speed_kmh=v, seed=seed, config=f.name, **params)
    os.unlink(f.name)
    dm = r.delta_m[np.isfinite(r.delta_m)]
    dur = dm.size * 0.01
    d = np.diff(dm)
    tv = float(np.sum(np.abs(d))) / dur
    dd = d[np.abs(d) > 1.0]
    chat = int(np.count_nonzero(np.sign(dd[1:]) != np.sign(dd[:-1]))) / dur
    out = {"case": case, "v": vname, "seed": seed, "tv": tv, "chat": chat,
           "beta": float(np.degrees(np.max(np.abs(r.truth["beta_rad"])))),
           "dev": float(np.max(np.abs(r.truth["lateral_dev_m"]))), "spun": r.spun}
    if case.startswith("c0"):
        k = adaptation_kpis(r.truth, 6.0)
        out["os"] = k.get("yaw_overshoot_degps")
    return out

if __name__ == "__main__":
    cases = sys.argv[1].split(","); seeds = [int(s) for s in sys.argv[2].split(",")]
    jobs = [(c, v, s) for c in cases for v in VARIANTS for s in seeds]
    with ProcessPoolExecutor(2) as ex:
        res = list(ex.map(one, jobs))
    json.dump(res, open(sys.argv[3], "w"))
    import collections
    agg = collections.defaultdict(list)
    for r in res:
        agg[(r["case"], r["v"])].append(r)
    for (c, v), rs in agg.items():
        med = lambda k: float(np.median([x[k] for x in rs if x.get(k) is not None])) if any(x.get(k) is not None for x in rs) else float("nan")
        print(f"{c:6s} {v:14s} tv {med('tv'):7.0f} chat {med('chat'):5.1f} beta {med('beta'):5.2f} dev {med('dev'):5.2f} os {med('os'):5.2f} spun {sum(x['spun'] for x in rs)}")
