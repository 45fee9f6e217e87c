"""plant_sim: the plant simulator (the project's stand-in for CarSim), pure Python.

Modules (one job each; SI units, ISO 8855 axes: x forward, y left, z up, + yaw = left;
wheel order FL, FR, RL, RR):

* ``tyre``       Magic Formula (Pacejka 2006, Table A3.1 205/60R15) with combined slip,
                 scaled to Table 1's axle cornering stiffnesses; ``make_vehicle_tyres()``.
* ``params``     ``params/vehicle.toml`` (+ ``params/tyre.toml``) -> ``VehicleParams``.
* ``motor``      in-wheel motor envelope (450 N·m, 45 kW per motor) and first-order lag.
* ``body``       planar body + roll + pitch (dynamic load transfer) + 4 wheel-spin DoF +
                 tyre relaxation; fixed 1 kHz step, semi-/linearly-implicit where stiff.
* ``road``       friction field (uniform, rectangular patches, split-mu).
* ``path``       reference path (projection: arc length, signed lateral deviation).
* ``course``     ISO 3888-1/-2 lane courses, curves, circles (cones and boundaries).
* ``driver``     preview path follower + speed holder; FMVSS 126 steering robots.
* ``sensors``    noise, bias, quantisation to the CAN resolution; vx/vy estimator model.
* ``scenario``   ``scenarios/NAME.toml`` or a user's file -> ``Scenario``; ``load_scenario``,
                 ``list_scenarios``.
* ``scenario_schema`` every key of a scenario file: type, unit, default, range (the checks).
* ``simulation`` ``Simulation`` (one comm cycle per ``step_comm``) and ``run_passive``.

``process.py`` (the CAN bus wrapper) lives alongside and is not part of the model.
"""
