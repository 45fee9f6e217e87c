/* Fault reaction (see node_fault.h). */
#include "node_fault.h"

#include <math.h>
#include <string.h>

#define RH_FAULT_TIME_TOL_S 1e-9 /* FaultyCore's tolerance on the window edges, s */
#define RH_QP_FAILED_STATUS 3    /* QpStatus.FAILED (mpc_qp.h RH_QP_FAILED) */

void rh_node_fault_default_config(rh_node_fault_config_t *cfg) {
  (void)memset(cfg, 0, sizeof *cfg);
  cfg->rampdown_nm_per_s = 1500.0;
}

static int fault_config_ok(const rh_node_fault_config_t *c) {
  int i;
  if (!(isfinite(c->rampdown_nm_per_s) && c->rampdown_nm_per_s >= 0.0)) {
    return 0;
  }
  if (c->n_windows < 0 || c->n_windows > RH_NODE_FAULT_WINDOWS) {
    return 0;
  }
  for (i = 0; i < c->n_windows; ++i) {
    if (!isfinite(c->window_start_s[i])) {
      return 0;
    }
    if (!(c->window_duration_s[i] >= 0.0)) { /* NaN fails too; +inf is allowed */
      return 0;
    }
  }
  return 1;
}

int rh_node_fault_init(rh_node_fault_t *f, const rh_node_fault_config_t *cfg,
                       double comm_period_s, double peak_torque_nm) {
  int i, ok = cfg != NULL && fault_config_ok(cfg) && isfinite(comm_period_s) &&
              comm_period_s > 0.0 && isfinite(peak_torque_nm) && peak_torque_nm > 0.0;
  (void)memset(f, 0, sizeof *f);
  if (!ok) {
    rh_node_fault_default_config(&f->cfg);
    f->latched = 1; /* no trustworthy parameters: the node starts in FAULT */
    f->peak_torque_nm = 0.0;
    f->ramp_step_nm = 0.0;
    return -1;
  }
  f->cfg = *cfg;
  for (i = 0; i < cfg->n_windows; ++i) {
    f->window_end_s[i] = cfg->window_start_s[i] + cfg->window_duration_s[i];
  }
  f->ramp_step_nm = cfg->rampdown_nm_per_s * comm_period_s;
  f->peak_torque_nm = peak_torque_nm;
  return 0;
}

int rh_node_fault_injected(rh_node_fault_t *f, double sim_time_s) {
  int i;
  for (i = 0; i < f->cfg.n_windows; ++i) {
    if (f->cfg.window_start_s[i] - RH_FAULT_TIME_TOL_S <= sim_time_s &&
        sim_time_s < f->window_end_s[i] - RH_FAULT_TIME_TOL_S) {
      f->injected += 1;
      return 1;
    }
  }
  return 0;
}

void rh_node_fault_latch(rh_node_fault_t *f) {
  f->exceptions += 1;
  f->latched = 1;
}

void rh_node_fault_outputs(const rh_node_fault_t *f, double accel_pedal, double brake_pedal,
                           rh_node_outputs_t *out) {
  double total = (accel_pedal - brake_pedal) * 4.0 * f->peak_torque_nm;
  int i;
  for (i = 0; i < 4; ++i) {
    out->torques[i] = total / 4.0;
  }
  out->total_torque = total;
  out->delta_m = 0.0;
  out->qp_status = RH_QP_FAILED_STATUS;
  out->qp_iterations = 0;
  out->fallback = 1;
  out->yaw_rate_ref = 0.0;
  out->beta_ref = 0.0;
}

void rh_node_fault_ramp_down(const rh_node_fault_t *f, double torques[4]) {
  double step = f->ramp_step_nm;
  int i;
  for (i = 0; i < 4; ++i) {
    double t = torques[i];
    torques[i] = (fabs(t) <= step || !isfinite(t)) ? 0.0 : t - copysign(step, t);
  }
}
