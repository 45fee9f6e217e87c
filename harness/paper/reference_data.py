"""The paper's own numbers, transcribed from rhonn_nmpc_paper.tex (Tables 2-5, Section IV text).

Units: Vx, Vy km/h; yaw rate deg/s; speeds km/h; step times ms; deviation m; angles deg.
"""

from __future__ import annotations

# Paper Tables 2 and 3: (min, max, RMSE) per model and state; Vx, Vy km/h, ωr deg/s.
PAPER_TABLE2 = {
    "7dof-li": {"vx_kmh": (0.26, 1.20, 0.64), "vy_kmh": (0.0, 0.77, 0.20),
                "yaw_rate_degps": (0.01, 7.54, 1.98)},
    "7dof-mf": {"vx_kmh": (0.60, 1.09, 0.78), "vy_kmh": (0.0, 0.69, 0.17),
                "yaw_rate_degps": (0.0, 6.13, 1.53)},
    "rhonn": {"vx_kmh": (0.03, 0.57, 0.06), "vy_kmh": (0.0, 0.64, 0.15),
              "yaw_rate_degps": (0.0, 8.07, 1.96)},
}
PAPER_TABLE3 = {
    "7dof-li": {"vx_kmh": (0.06, 3.86, 3.05), "vy_kmh": (0.0, 18.62, 3.97),
                "yaw_rate_degps": (0.01, 50.27, 10.22)},
    "7dof-mf": {"vx_kmh": (0.04, 2.08, 0.86), "vy_kmh": (0.01, 17.92, 4.14),
                "yaw_rate_degps": (0.0, 32.33, 6.67)},
    "rhonn": {"vx_kmh": (0.01, 0.57, 0.12), "vy_kmh": (0.0, 4.16, 0.65),
              "yaw_rate_degps": (0.0, 11.75, 2.29)},
}
PAPER_TABLE4_KMH = {"nmpc-rhonn": 74.4, "nmpc-mf": 72.4, "lmpc": 62.8}
PAPER_TABLE5_MS = {"dlc": {"nmpc-rhonn": 0.0166, "nmpc-mf": 0.0193, "lmpc": 0.0166},
                   "curve": {"nmpc-rhonn": 0.0172, "nmpc-mf": 0.0194, "lmpc": 0.0171}}
PAPER_CURVE = {"lmpc": {"max_abs_lateral_dev_m": 2.68, "max_abs_swa_deg": 394.0}}
MODELS = ("7dof-li", "7dof-mf", "rhonn")
STATES = (("vx_kmh", "Vx [km/h]"), ("vy_kmh", "Vy [km/h]"), ("yaw_rate_degps", "ωr [deg/s]"))
