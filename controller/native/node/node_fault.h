/* Fault reaction of the node (Python reference: controller/runtime/node.py,
 * ControllerNode._run_controller / _fault_outputs / _ramp_down, and the injected core faults
 * of controller/runtime/core_fault.py, FaultyCore).
 *
 * * FAULT: the core failed. It is latched: the core is not stepped again until the node is
 *   initialised again (its state may be half-updated). The safe output is the driver's total
 *   torque Tt = (accel - brake) x 4 x T_peak split evenly over the four wheels, Delta M = 0,
 *   QP failed, fallback flagged, references 0 (the car without the stability function).
 *   The C core never fails by itself (rh_ctrl_step has no error path); FAULT comes from an
 *   injected core fault (a window of simulated time, ``--fault core-exception:D@T``), from
 *   a core the integrator could not initialise (no core given), or from the integrator
 *   (rh_node_fault_latch, e.g. a failed self-test).
 * * Ramp-down (driver frame lost): every wheel torque moves towards 0 N m by
 *   rampdown_nm_per_s x comm_period_s per answer; a non-finite torque becomes 0. */
#ifndef RH_NODE_FAULT_H
#define RH_NODE_FAULT_H

#include <stdint.h>

#define RH_NODE_FAULT_WINDOWS 4 /* injected core-fault windows */

/* The controller's outputs as the node holds them (Python: ControllerOutputs; the core's
 * rh_outputs_t widened to double). */
typedef struct {
  double torques[4];   /* wheel torque commands FL FR RL RR, N m */
  double total_torque; /* driver's Tt, N m */
  double delta_m;      /* Delta M = T2 + T4 - T1 - T3, N m */
  double yaw_rate_ref; /* rad/s */
  double vy_ref;       /* m/s */
  double beta_ref;     /* rad */
  int qp_status;       /* RH_QP_* (QpStatus) */
  int qp_iterations;   /* solver iterations this step */
  int fallback;        /* the solver failed and the fallback Delta M was used */
} rh_node_outputs_t;

typedef struct {
  double rampdown_nm_per_s;                 /* ramp-down rate, N m/s (>= 0), default 1500 */
  int n_windows;                            /* injected core-fault windows in use, 0..4 */
  double window_start_s[RH_NODE_FAULT_WINDOWS];    /* simulated time T, s */
  double window_duration_s[RH_NODE_FAULT_WINDOWS]; /* D, s (HUGE_VAL: until the end) */
} rh_node_fault_config_t;

typedef struct {
  rh_node_fault_config_t cfg;
  double window_end_s[RH_NODE_FAULT_WINDOWS]; /* T + D, s */
  double ramp_step_nm;   /* ramp-down per answer, N m */
  double peak_torque_nm; /* per motor, N m */
  int latched;           /* FAULT latched */
  int64_t exceptions;    /* times the core failed (node.py controller_exceptions) */
  int64_t injected;      /* injected core faults raised (FaultyCore.raised) */
} rh_node_fault_t;

void rh_node_fault_default_config(rh_node_fault_config_t *cfg);
/* 0 on success; -1 for an invalid config (rate not finite or < 0, n_windows outside 0..4,
 * a window start not finite or a duration NaN or < 0, comm period or peak torque not > 0):
 * then no injection, the default rate, and the fault latched (the safe state). */
int rh_node_fault_init(rh_node_fault_t *f, const rh_node_fault_config_t *cfg,
                       double comm_period_s, double peak_torque_nm);
/* 1 (counted) when an injected core fault is active at simulated time ``sim_time_s`` s:
 * T - 1e-9 <= t < T + D - 1e-9 (FaultyCore._check). */
int rh_node_fault_injected(rh_node_fault_t *f, double sim_time_s);
/* The core failed: count it and latch FAULT. */
void rh_node_fault_latch(rh_node_fault_t *f);
/* FAULT's safe output from the pedals (0..1) into *out (vy_ref is left as it is). */
void rh_node_fault_outputs(const rh_node_fault_t *f, double accel_pedal, double brake_pedal,
                           rh_node_outputs_t *out);
/* One answer of ramp-down on torques[4] N m, in place. */
void rh_node_fault_ramp_down(const rh_node_fault_t *f, double torques[4]);

#endif /* RH_NODE_FAULT_H */
