/* The node's per-cycle logic (see node_logic.h; Python: controller/runtime/node.py). */
#include "node_logic.h"

#include <math.h>
#include <string.h>

/* math.radians / math.degrees of the reference: x * (pi / 180), x * (180 / pi). */
#define RH_NODE_PI 3.14159265358979323846
static const double deg_to_rad = RH_NODE_PI / 180.0;
static const double rad_to_deg = 180.0 / RH_NODE_PI;

/* The sensor streams whose validity makes sensors_ok (node.py SENSOR_FRAMES). */
static const int sensor_streams[3] = {RH_MON_MOTION, RH_MON_WHEELS, RH_MON_VEHICLE_EST};

#define SYNC_CYCLE 0    /* SYNC values: CYCLE, SIM_TIME */
#define SYNC_TIME 1

void rh_node_logic_default_config(rh_node_logic_config_t *cfg) {
  int i;
  (void)memset(cfg, 0, sizeof *cfg);
  cfg->comm_period_s = 0.01;
  cfg->mpc_every = 5;
  cfg->controller_id = 15;
  cfg->peak_torque_nm = 450.0;
  cfg->peak_power_w = 45000.0;
  cfg->plant_restart_backstep_s = 0.5;
  for (i = 0; i < RH_NODE_DATA_STREAMS; ++i) {
    cfg->burst_bound[i] = 3;
  }
  rh_node_monitor_default_config(&cfg->monitor);
  rh_node_plaus_default_config(&cfg->plaus);
  rh_node_envelope_default_config(&cfg->envelope);
  rh_node_fault_default_config(&cfg->fault);
}

static int logic_config_ok(const rh_node_logic_config_t *c) {
  int i;
  if (!(isfinite(c->comm_period_s) && c->comm_period_s > 0.0)) {
    return 0;
  }
  if (c->mpc_every < 1 || c->controller_id < 0 || c->controller_id > 15) {
    return 0;
  }
  if (!(isfinite(c->plant_restart_backstep_s) && c->plant_restart_backstep_s >= 0.0)) {
    return 0;
  }
  for (i = 0; i < RH_NODE_DATA_STREAMS; ++i) {
    if (c->burst_bound[i] < 1 || c->burst_bound[i] > RH_NODE_BURST_MAX) {
      return 0;
    }
  }
  return 1;
}

int rh_node_logic_init(rh_node_logic_t *st, const rh_node_logic_config_t *cfg) {
  rh_node_logic_config_t def;
  const rh_node_logic_config_t *c = cfg;
  int ok = cfg != NULL && logic_config_ok(cfg);
  (void)memset(st, 0, sizeof *st);
  if (!ok) {
    rh_node_logic_default_config(&def);
    c = &def;
  }
  st->cfg = *c;
  /* each module falls back to its own safe defaults; any failure latches FAULT below */
  ok = (rh_node_monitor_init(&st->monitor, cfg != NULL ? &cfg->monitor : NULL) == 0) && ok;
  ok = (rh_node_plaus_init(&st->plaus, cfg != NULL ? &cfg->plaus : NULL) == 0) && ok;
  ok = (rh_node_envelope_init(&st->envelope, cfg != NULL ? &cfg->envelope : NULL,
                              c->peak_torque_nm, c->peak_power_w, c->comm_period_s) == 0) && ok;
  ok = (rh_node_fault_init(&st->fault, cfg != NULL ? &cfg->fault : NULL, c->comm_period_s,
                           c->peak_torque_nm) == 0) && ok;
  st->inputs.stab_enable = 1; /* ControllerInputs' defaults */
  st->inputs.sensors_valid = 1;
  st->out.qp_status = RH_QP_NOT_RUN;
  st->mode = RH_NODE_MODE_INIT;
  st->cycles_since_mpc = st->cfg.mpc_every; /* the full step on the first valid cycle */
  if (!ok) {
    st->fault.latched = 1;
  }
  return ok ? 0 : -1;
}

/* Rx validation, then the frozen-signal check on an accepted sensor frame (node.py
 * _accept); the speed of the check is the vx the core saw last. RH_MON_* result. */
static int accept(rh_node_logic_t *st, const rh_node_rx_t *ev, double now_s) {
  int r;
  if (ev->kind == RH_NODE_RX_REJECTED) {
    rh_node_monitor_reject(&st->monitor, ev->reason, ev->stream);
    return ev->reason;
  }
  if (ev->kind == RH_NODE_RX_IGNORED) {
    rh_node_monitor_ignore(&st->monitor);
    return RH_MON_BAD_EVENT;
  }
  if (ev->kind != RH_NODE_RX_DECODED) {
    st->bad_events += 1;
    return RH_MON_BAD_EVENT;
  }
  r = rh_node_monitor_process(&st->monitor, ev->stream, &ev->frame, now_s);
  if (r == RH_MON_ACCEPTED && rh_node_plaus_checked(ev->stream) > 0) {
    rh_node_plaus_update(&st->plaus, ev->stream, ev->frame.values, st->inputs.vx);
  }
  return r;
}

int rh_node_logic_rx(rh_node_logic_t *st, const rh_node_rx_t *ev) {
  int s, n;
  if (ev == NULL || ev->stream == RH_MON_SYNC || ev->stream < -1 ||
      ev->stream >= RH_MON_STREAMS) {
    st->bad_events += 1;
    return -1;
  }
  s = ev->stream;
  if (ev->kind == RH_NODE_RX_REJECTED || ev->kind == RH_NODE_RX_IGNORED) {
    (void)accept(st, ev, st->last_stamp_s); /* counted now, never buffered (no time needed) */
    return 0;
  }
  if (ev->kind != RH_NODE_RX_DECODED || s < 0) { /* a decoded frame needs its stream */
    st->bad_events += 1;
    return -1;
  }
  n = st->burst_n[s];
  if (n == st->cfg.burst_bound[s]) { /* drop the oldest: the newest belongs to the SYNC */
    st->burst_drops += 1;
    (void)memmove(&st->burst[s][0], &st->burst[s][1],
                  ((size_t)n - 1u) * sizeof st->burst[s][0]);
    n -= 1;
  }
  st->burst[s][n] = ev->frame;
  st->burst_n[s] = n + 1;
  return 0;
}

/* Simulated time went backwards: a new plant. Every stream's state is forgotten (its
 * frames must prove themselves again); the learned core state is kept but for the model's
 * pending one-step prediction, which belongs to the old plant's time line. */
static void plant_restarted(rh_node_logic_t *st, rh_ctrl_t *ctrl) {
  st->plant_restarts += 1;
  if (ctrl != NULL && ctrl->kind == RH_CTRL_NMPC_RHONN) {
    ctrl->u.rhonn.model.has_record = 0;
  }
  rh_node_monitor_restart(&st->monitor);
  rh_node_plaus_reset(&st->plaus);
}

int rh_node_logic_sync_begin(rh_node_logic_t *st, rh_ctrl_t *ctrl, const rh_node_rx_t *sync) {
  int s, i, has_now;
  double now = 0.0, stamp;
  if (sync == NULL || sync->stream != RH_MON_SYNC ||
      (sync->kind != RH_NODE_RX_DECODED && sync->kind != RH_NODE_RX_REJECTED)) {
    st->bad_events += 1;
    return -1;
  }
  has_now = sync->kind == RH_NODE_RX_DECODED;
  if (has_now) {
    now = sync->frame.values[SYNC_TIME];
  }
  stamp = has_now ? now : (st->has_sync ? st->last_sync.values[SYNC_TIME] : 0.0);
  if (st->has_sync && has_now &&
      now < st->last_sync.values[SYNC_TIME] - st->cfg.plant_restart_backstep_s) {
    plant_restarted(st, ctrl);
  }
  st->last_stamp_s = stamp;
  for (s = 0; s < RH_NODE_DATA_STREAMS; ++s) { /* per stream in arrival order */
    rh_node_rx_t ev;
    ev.kind = RH_NODE_RX_DECODED;
    ev.stream = s;
    ev.reason = 0;
    for (i = 0; i < st->burst_n[s]; ++i) {
      ev.frame = st->burst[s][i];
      (void)accept(st, &ev, stamp);
    }
    st->burst_n[s] = 0;
  }
  return 0;
}

int rh_node_logic_sync_end(rh_node_logic_t *st, rh_ctrl_t *ctrl, const rh_node_rx_t *sync,
                           rh_node_tx_t *tx) {
  if (accept(st, sync, st->last_stamp_s) != RH_MON_ACCEPTED) {
    return 0; /* a rejected SYNC is not answered: the plant's timeout handles it */
  }
  st->has_sync = 1;
  st->last_sync = sync->frame;
  rh_node_logic_answer(st, ctrl, st->last_stamp_s, tx);
  return 1;
}

int rh_node_logic_sync(rh_node_logic_t *st, rh_ctrl_t *ctrl, const rh_node_rx_t *sync,
                       const rh_node_rx_t *released, int n_released, rh_node_tx_t *tx) {
  int i;
  if (rh_node_logic_sync_begin(st, ctrl, sync) != 0) return -1;
  if (released != NULL) {
    for (i = 0; i < n_released; ++i) {
      (void)accept(st, &released[i], st->last_stamp_s);
    }
  }
  return rh_node_logic_sync_end(st, ctrl, sync, tx);
}

int rh_node_logic_accept(rh_node_logic_t *st, const rh_node_rx_t *ev, double now_s) {
  int r;
  if (ev == NULL || ev->stream < -1 || ev->stream >= RH_MON_STREAMS ||
      (ev->kind == RH_NODE_RX_DECODED && ev->stream < 0) ||
      (ev->kind != RH_NODE_RX_DECODED && ev->kind != RH_NODE_RX_REJECTED &&
       ev->kind != RH_NODE_RX_IGNORED)) {
    st->bad_events += 1;
    return -1;
  }
  r = accept(st, ev, now_s);
  if (r == RH_MON_ACCEPTED && ev->kind == RH_NODE_RX_DECODED && ev->stream == RH_MON_SYNC) {
    st->has_sync = 1;
    st->last_sync = ev->frame;
  }
  return 0;
}

void rh_node_logic_tick(rh_node_logic_t *st, rh_ctrl_t *ctrl, double now_s, rh_node_tx_t *tx) {
  rh_node_logic_answer(st, ctrl, now_s, tx);
}

void rh_node_logic_set_secoc_evicted(rh_node_logic_t *st, int64_t total) {
  st->secoc_evicted = total;
}

/* The core's view of the bus from the latest accepted frames (node.py _fill_inputs). */
static void fill_inputs(rh_node_logic_t *st, int sensors_ok) {
  rh_node_inputs_t *in = &st->inputs;
  const rh_node_frame_t *f = rh_node_monitor_latest(&st->monitor, RH_MON_DRIVER);
  if (f != NULL) {
    in->swa_rad = f->values[0] * deg_to_rad;
    in->accel_pedal = f->values[1] / 100.0;
    in->brake_pedal = f->values[2] / 100.0;
    in->stab_enable = f->values[3] != 0.0; /* truth value: NaN counts as set, as bool() */
  }
  f = rh_node_monitor_latest(&st->monitor, RH_MON_MOTION);
  if (f != NULL) {
    in->yaw_rate = f->values[0] * deg_to_rad;
    in->ax = f->values[1];
    in->ay = f->values[2];
  }
  f = rh_node_monitor_latest(&st->monitor, RH_MON_WHEELS);
  if (f != NULL) {
    int i;
    for (i = 0; i < 4; ++i) {
      in->wheel_speeds[i] = f->values[i];
    }
  }
  f = rh_node_monitor_latest(&st->monitor, RH_MON_VEHICLE_EST);
  if (f != NULL) {
    in->vx = f->values[0];
    in->vy = f->values[1];
  }
  in->sensors_valid = sensors_ok;
}

/* ControllerInputs -> rh_inputs_t, as the Python binding converts it (real_t per value). */
static void core_inputs(const rh_node_inputs_t *n, rh_inputs_t *in) {
  int i;
  in->swa_rad = (real_t)n->swa_rad;
  in->accel_pedal = (real_t)n->accel_pedal;
  in->brake_pedal = (real_t)n->brake_pedal;
  in->yaw_rate = (real_t)n->yaw_rate;
  in->ax = (real_t)n->ax;
  in->ay = (real_t)n->ay;
  for (i = 0; i < 4; ++i) {
    in->wheel_speeds[i] = (real_t)n->wheel_speeds[i];
  }
  in->vx = (real_t)n->vx;
  in->vy = (real_t)n->vy;
  in->stab_enable = n->stab_enable != 0;
  in->sensors_valid = n->sensors_valid != 0;
  in->wheel_speeds_usable = 1;
}

static void widen_outputs(const rh_outputs_t *o, rh_node_outputs_t *out) {
  int i;
  for (i = 0; i < 4; ++i) {
    out->torques[i] = (double)o->torques[i];
  }
  out->total_torque = (double)o->total_torque;
  out->delta_m = (double)o->delta_m;
  out->yaw_rate_ref = (double)o->yaw_rate_ref;
  out->vy_ref = (double)o->vy_ref;
  out->beta_ref = (double)o->beta_ref;
  out->qp_status = o->qp_status;
  out->qp_iterations = o->qp_iterations;
  out->fallback = o->fallback != 0;
}

/* The core's step or its skip (node.py _run_controller): the mode of this answer; the
 * outputs in st->out. */
static int run_controller(rh_node_logic_t *st, rh_ctrl_t *ctrl, int sensors_ok,
                          double sim_time_s, int *mpc_update) {
  int mode, full;
  rh_inputs_t in;
  rh_outputs_t o;
  if (st->fault.latched) {
    rh_node_fault_outputs(&st->fault, st->inputs.accel_pedal, st->inputs.brake_pedal, &st->out);
    return RH_NODE_MODE_FAULT;
  }
  if (!sensors_ok) {
    mode = RH_NODE_MODE_DEGRADED_SENSORS;
  } else if (!st->inputs.stab_enable) {
    mode = RH_NODE_MODE_STANDBY;
  } else {
    mode = RH_NODE_MODE_ACTIVE;
  }
  st->cycles_since_mpc += 1;
  full = st->cycles_since_mpc >= st->cfg.mpc_every;
  if (full) {
    st->cycles_since_mpc = 0;
    *mpc_update = 1;
  }
  if (ctrl == NULL || rh_node_fault_injected(&st->fault, sim_time_s)) {
    rh_node_fault_latch(&st->fault); /* the core failed: FAULT until the node restarts */
    rh_node_fault_outputs(&st->fault, st->inputs.accel_pedal, st->inputs.brake_pedal, &st->out);
    return RH_NODE_MODE_FAULT;
  }
  core_inputs(&st->inputs, &in);
  if (full) {
    rh_ctrl_step(ctrl, &in, &o);
  } else {
    rh_ctrl_allocate_only(ctrl, &in, &o);
  }
  widen_outputs(&o, &st->out);
  return mode;
}

/* True when a bounded rx queue dropped frames since the previous answer. */
static int rx_overloaded(rh_node_logic_t *st) {
  int64_t total = st->burst_drops + st->secoc_evicted;
  if (total == st->drops_answered) {
    return 0;
  }
  st->drops_answered = total;
  st->rx_overload_cycles += 1;
  return 1;
}

void rh_node_logic_answer(rh_node_logic_t *st, rh_ctrl_t *ctrl, double now_s,
                          rh_node_tx_t *tx) {
  int i, driver_ok, sensors_ok, sync_ok, mode, clipped, mpc_update = 0;
  unsigned fault_bits = 0u;
  double c_val = st->last_sync.values[SYNC_CYCLE];
  /* CYCLE is 0..2^24-1 from the decoder; anything else (no valid integer) echoes as no SYNC */
  int64_t cycle = (st->has_sync && c_val >= 0.0 && c_val < 9.0e15) ? (int64_t)c_val : -1;
  double sim_time = st->has_sync ? st->last_sync.values[SYNC_TIME] : 0.0;
  double *t = st->torques;
  driver_ok = rh_node_monitor_valid(&st->monitor, RH_MON_DRIVER, now_s);
  sensors_ok = 1;
  for (i = 0; i < 3; ++i) { /* every stream checked (and its timeout counted) */
    sensors_ok = rh_node_monitor_valid(&st->monitor, sensor_streams[i], now_s) && sensors_ok;
  }
  sensors_ok = sensors_ok && !rh_node_plaus_any_faulty(&st->plaus);
  sync_ok = rh_node_monitor_valid(&st->monitor, RH_MON_SYNC, now_s);
  fill_inputs(st, sensors_ok);
  if (!sensors_ok) {
    fault_bits |= 1u << RH_NODE_BIT_SENSORS_INVALID;
  }
  if (!driver_ok) {
    fault_bits |= 1u << RH_NODE_BIT_DRIVER_INVALID;
  }
  if (!sync_ok) {
    fault_bits |= 1u << RH_NODE_BIT_SYNC_LOST;
  }
  if (!driver_ok) { /* the driver's torque is unknown: ramp down (also in FAULT) */
    mode = st->mode != RH_NODE_MODE_INIT ? RH_NODE_MODE_DRIVER_LOST_RAMPDOWN
                                         : RH_NODE_MODE_INIT;
    rh_node_fault_ramp_down(&st->fault, t);
    st->out.delta_m = 0.0;
    st->out.qp_status = RH_QP_NOT_RUN;
    st->out.qp_iterations = 0;
  } else {
    mode = run_controller(st, ctrl, sensors_ok, sim_time, &mpc_update);
    for (i = 0; i < 4; ++i) {
      t[i] = st->out.torques[i];
    }
  }
  clipped = rh_node_envelope_apply(&st->envelope, t, st->inputs.wheel_speeds,
                                   !(sensors_ok && st->inputs.stab_enable), st->env_prev, t);
  for (i = 0; i < 4; ++i) {
    st->env_prev[i] = t[i];
  }
  if (clipped) {
    fault_bits |= 1u << RH_NODE_BIT_TORQUE_CLIPPED;
  }
  if (st->out.fallback) {
    fault_bits |= 1u << RH_NODE_BIT_SOLVER_FALLBACK;
  }
  if (mode != st->mode) {
    st->mode_changes += 1;
  }
  st->mode = mode;
  if (rx_overloaded(st)) {
    fault_bits |= 1u << RH_NODE_BIT_RX_OVERLOAD;
  }

  for (i = 0; i < 4; ++i) {
    tx->tq_nm[i] = t[i];
  }
  tx->echo_cycle = cycle >= 0 ? (int)(cycle % 256) : 0;
  tx->mode = mode;
  tx->fault_bits = (int)fault_bits; /* 8 bits */
  tx->qp_status = st->out.qp_status;
  tx->qp_iter = st->out.qp_iterations;
  tx->compute_time_us = 0.0;
  tx->controller_id = st->cfg.controller_id;
  tx->delta_m_nm = t[1] + t[3] - t[0] - t[2];
  tx->yaw_rate_ref_deg_s = st->out.yaw_rate_ref * rad_to_deg;
  tx->beta_ref_deg = st->out.beta_ref * rad_to_deg;
  tx->cycle = cycle;
  tx->sim_time_s = sim_time;
  tx->mpc_update = mpc_update;
  st->last_tx = *tx;
}

void rh_node_logic_sizes(int64_t out[4]) {
  out[0] = (int64_t)sizeof(rh_node_logic_t);
  out[1] = (int64_t)sizeof(rh_node_logic_config_t);
  out[2] = (int64_t)sizeof(rh_node_tx_t);
  out[3] = (int64_t)sizeof(rh_node_rx_t);
}
