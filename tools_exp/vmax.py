import json, os, sys, tempfile
from concurrent.futures import ProcessPoolExecutor
import numpy as np
sys.path.insert(0, "/work/main")
from harness.paper.benchmark import controller_config_text, PERTURBED
from harness.run.inprocess_loop import run_in_process
from harness.analysis.stability import evaluate
VARIANTS = json.loads(os.environ["VARIANTS"])

def passes(vname, seed, v, vehicle):
    text = controller_config_text(seed, VARIANTS[vname])
    with tempfile.NamedTemporaryFile("w", suffix=".toml", delete=False) as f:
        f.write(text)
    ctrl = "lmpc" if vname == "lmpc" else "nmpc-rhonn"
    r = run_in_process("dlc-paper", ctrl, speed_kmh=v, seed=seed, config=f.name, vehicle=vehicle)
    os.unlink(f.name)
    truth = dict(r.truth)
    out = evaluate("dlc", truth, scenario="dlc-paper", speed_kmh=v, vehicle=vehicle)
    return bool(out["paper"])

def bisect(job):
    vname, seed, car = job
    vehicle = dict(PERTURBED) if car == "pert" else {}
    lo, hi = 60.0, 90.0
    if not passes(vname, seed, lo, vehicle):
        return (vname, seed, car, None)
    if passes(vname, seed, hi, vehicle):
        return (vname, seed, car, hi)
    while hi - lo > 0.5 + 1e-9:
        mid = round((lo + hi) / 2 / 0.5) * 0.5
        if mid in (lo, hi):
            break
        if passes(vname, seed, mid, vehicle):
            lo = mid
        else:
            hi = mid
    return (vname, seed, car, lo)

if __name__ == "__main__":
    seeds = [int(s) for s in sys.argv[1].split(",")]
    jobs = [(v, s, c) for v in VARIANTS for c in ("nom", "pert") for s in seeds]
    with ProcessPoolExecutor(2) as ex:
        res = list(ex.map(bisect, jobs))
    json.dump(res, open(sys.argv[2], "w"))
    for v in VARIANTS:
        nom = [r[3] for r in res if r[0] == v and r[2] == "nom"]
        per = [r[3] for r in res if r[0] == v and r[2] == "pert"]
        print(f"{v:10s} nominal {nom} med {np.median(nom)}  perturbed {per} med {np.median(per)}  loss {np.median(nom)-np.median(per)}")
